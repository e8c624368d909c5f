"""Collect whole episodes from B environments into preallocated `(T, B, n, ...)` arrays.

Every batch plays B fresh episodes from their first step to their end, so returns are Monte Carlo
over whole episodes (paper IV; truncation at `max_steps` ends an episode with no further reward).
Steps after a slot's episode ended are padding, marked invalid.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from bitcomm.config import TaskConfig
from bitcomm.envs.vec import Observation, VecGoalExchange
from bitcomm.policies.agent import act
from bitcomm.policies.evaluation import play_first_episodes
from bitcomm.policies.networks import PolicyNet


class Rollout(NamedTuple):
    """B whole episodes, time-major: the tensor contract of the learning core. Tensors share memory with
    the collector's buffers.

    The estimators read only `rewards`, `done`, `valid`, `dropped` (and the critics' baselines); the
    objective terms read `moves`, `bits`, `logp_*` and `valid`; the networks read `planes`, `received`
    (policy) and `state`, `moves`, `received` (critics). `T` steps, `B` episodes, `n` agents, `K` bits,
    `slots` messages an agent hears per step. The observation fields are the grid task's: `planes`
    (own position and seen goal, `2 x S x S`) and `state` (every agent's planes) are what another task
    replaces, with an encoder for its observations (`ModelConfig.encoder`); `goal` is read only by the
    auxiliary terms. Everything else is per-agent and task-agnostic.
    """

    planes: torch.Tensor  # (T, B, n, 2, S, S) uint8
    received: torch.Tensor  # (T, B, n, slots, K) uint8
    state: torch.Tensor  # (T, B, 2n, S, S) uint8
    moves: torch.Tensor  # (T, B, n) int64
    bits: torch.Tensor  # (T, B, n, K) uint8, as sent
    logp_move: torch.Tensor  # (T, B, n) at acting time
    logp_message: torch.Tensor  # (T, B, n)
    dropped: torch.Tensor  # (T, B, n) bool
    rewards: torch.Tensor  # (T, B) team reward
    done: torch.Tensor  # (T, B) bool, the episode ended after this step
    valid: torch.Tensor  # (T, B) bool
    goal: torch.Tensor  # (B, n) int64, each agent's own goal cell (privileged: training-time only)
    sent_greedy: torch.Tensor  # (B,) bool, every sender sent its most likely message (TrainConfig.greedy_senders)
    length: np.ndarray  # (B,) episode lengths
    team_return: np.ndarray  # (B,)
    success: np.ndarray  # (B,)


class Collector:
    """Plays batches of B first episodes with a policy network, sampling as it was trained."""

    def __init__(self, task: TaskConfig, num_envs: int) -> None:
        self.task, self.num_envs = task, num_envs
        T, B = task.env.max_steps, num_envs
        n, S, K, slots = task.env.n_agents, task.env.size, task.channel.bits, task.slots
        self.planes = np.zeros((T, B, n, 2, S, S), dtype=np.uint8)
        self.received = np.zeros((T, B, n, slots, K), dtype=np.uint8)
        self.state = np.zeros((T, B, 2 * n, S, S), dtype=np.uint8)
        self.moves = np.zeros((T, B, n), dtype=np.int64)
        self.bits = np.zeros((T, B, n, K), dtype=np.uint8)
        self.logp = np.zeros((2, T, B, n), dtype=np.float32)
        self.dropped = np.zeros((T, B, n), dtype=bool)
        self.rewards = np.zeros((T, B), dtype=np.float32)
        self.done = np.zeros((T, B), dtype=bool)
        self.valid = np.zeros((T, B), dtype=bool)

    def collect(
        self,
        net: PolicyNet,
        seed: np.random.SeedSequence,
        generator: torch.Generator,
        greedy_senders: int = 0,
        held_messages: int = 0,
    ) -> Rollout:
        """B first episodes; in the first `greedy_senders` of them every sender sends its most likely message, and in
        the next `held_messages` each sender sends, at every step, the word it drew at the first."""
        env = VecGoalExchange(self.task, self.num_envs, seed=seed)
        goal = env.core.goal.copy()
        B, n = self.num_envs, self.task.env.n_agents
        length, team_return, success = np.zeros(B, np.int64), np.zeros(B), np.zeros(B, bool)
        t = 0
        running = np.ones(B, dtype=bool)  # slots whose first episode has not ended: the only ones the policy plays
        column = torch.arange(B)
        sent_greedy = column < greedy_senders
        held = (column >= greedy_senders) & (column < greedy_senders + held_messages)
        if held_messages and net.message_trunk is None:
            raise AssertionError("held messages need a message head that reads only the observed goal")
        # a message head of its own reads only the observed goal, which each slot's (first) episode keeps: its
        # logits are computed at the first step, for every step (a third to a half of acting's cost per step)
        episode_logits: torch.Tensor | None = None
        held_bits: torch.Tensor | None = None  # (B, n, K) the words drawn at the first step, for `held` columns

        def policy(obs: Observation) -> tuple[np.ndarray, np.ndarray]:
            nonlocal episode_logits, held_bits
            self.planes[t], self.received[t], self.state[t] = obs.planes, obs.received, obs.state
            if t == 0 and net.message_trunk is not None:
                with torch.no_grad():
                    logits = net.observed_message_logits(torch.from_numpy(obs.planes).flatten(0, 1))
                episode_logits = logits.view(B, n, -1)
                if held_messages:
                    held_bits = net.head.sample(logits, generator).view(B, n, -1)
            # late in training most first episodes end long before the batch's last one: a slot's later
            # episodes are never learned from, so they are not acted for (they stand still, silent)
            rows = slice(None) if running.all() else np.flatnonzero(running)
            greedy = sent_greedy[rows].repeat_interleave(n) if greedy_senders else None
            moves, bits, lp_move, lp_msg = act(
                net,
                torch.from_numpy(self.planes[t][rows]).flatten(0, 1),
                torch.from_numpy(self.received[t][rows]).flatten(0, 1),
                generator=generator,
                greedy_messages=greedy,
                message_logits=None if episode_logits is None else episode_logits[rows].flatten(0, 1),
                held_messages=None
                if held_bits is None
                else (held[rows].repeat_interleave(n), held_bits[rows].flatten(0, 1)),
            )
            for buffer, x in zip(
                (self.moves[t], self.bits[t], self.logp[0, t], self.logp[1, t]),
                (moves, bits, lp_move, lp_msg),
                strict=True,
            ):
                if isinstance(rows, np.ndarray):
                    buffer.fill(0)
                buffer[rows] = x.view(-1, *buffer.shape[1:]).numpy()
            return self.moves[t], self.bits[t]

        for step in play_first_episodes(env, policy):
            fin = step.result.finished
            self.rewards[t] = step.result.team_reward
            self.dropped[t] = step.dropped
            self.valid[t] = step.active
            self.done[t] = False
            first = step.active[fin.env_index]
            idx = fin.env_index[first]
            self.done[t, idx] = True
            running[idx] = False
            length[idx], team_return[idx], success[idx] = fin.length[first], fin.team_return[first], fin.success[first]
            t += 1

        def view(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a[:t])

        return Rollout(
            view(self.planes), view(self.received), view(self.state), view(self.moves), view(self.bits),
            torch.from_numpy(self.logp[0, :t]), torch.from_numpy(self.logp[1, :t]), view(self.dropped),
            view(self.rewards), view(self.done), view(self.valid), torch.from_numpy(goal), sent_greedy,
            length, team_return, success,
        )  # fmt: skip
