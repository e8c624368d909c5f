"""The grid world and its channel stepped together: what a batch of policies sees and does.

Episodes reset themselves (grid and messages in flight) when they end. With `autoreset=False` a
finished episode keeps its terminal observation until `reset(mask)`; the PettingZoo view uses that.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from bitcomm.channel.core import Channel
from bitcomm.config import TaskConfig
from bitcomm.envs.core import GoalExchangeCore, StepResult
from bitcomm.errors import bad_value, check_instance, is_integer


class Observation(NamedTuple):
    """What the B x n agents and their critics see at one step (views of live buffers: copy to keep)."""

    planes: np.ndarray  # (B, n, 2, S, S) uint8: own position, observed goal
    received: np.ndarray  # (B, n, slots, K) uint8: messages arriving now
    state: np.ndarray  # (B, 2n, S, S) uint8: every position, then every goal (critics only)
    t: np.ndarray  # (B,) int: steps already taken in the episode


class VecGoalExchange:
    """B self-resetting episodes of the goal-exchange task with its K-bit channel.

    Stepping it by hand (what `bitcomm.learn.rollout` and `bitcomm.policies.evaluation` do, batched)::

        env = VecGoalExchange(TaskConfig(), num_envs=8, seed=0)   # episodes already started
        obs = env.reset()                                         # or env.observe(): the same thing now
        for _ in range(100):
            moves = np.zeros((8, n), dtype=np.int64)              # (B, n) move indices (`envs.core.MOVE_NAMES`)
            bits = np.zeros((8, n, K), dtype=np.uint8)            # (B, n, K) the bits each agent sends
            result, dropped = env.step(moves, bits)               # rewards, terminated/truncated, finished
            obs = env.observe()                                   # ended episodes have restarted already

    An observation is a view of live buffers: copy what you keep across steps.
    """

    def __init__(
        self,
        task: TaskConfig,
        num_envs: int,
        seed: int | np.random.SeedSequence | None = None,
        autoreset: bool = True,
    ) -> None:
        check_instance("task", task, TaskConfig, "a bitcomm.TaskConfig, e.g. TaskConfig(EnvConfig(size=4))")
        if not is_integer(num_envs) or num_envs < 1:
            raise bad_value("num_envs", num_envs, "must be an integer >= 1 (episodes stepped side by side)")
        if not (seed is None or isinstance(seed, np.random.SeedSequence) or (is_integer(seed) and seed >= 0)):
            raise bad_value("seed", seed, "must be None, an integer >= 0 or a numpy SeedSequence")
        self.task = task
        self.num_envs = num_envs
        self.autoreset = autoreset
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        env_seed, channel_seed = seq.spawn(2)
        self.core = GoalExchangeCore(task.env, num_envs, seed=env_seed, autoreset=autoreset)
        self.channel = Channel.for_task(task, num_envs, seed=channel_seed)
        self._received = self.channel.received()

    def reset(self, mask: np.ndarray | None = None) -> Observation:
        """Start new episodes in the slots of `mask` (every slot when None), with no messages in flight;
        returns the observation of every slot (as `observe()`), so a hand-written loop starts from it."""
        self.core.reset(mask)
        self.channel.reset(mask)
        self._received = self.channel.received()
        return self.observe()

    def observe(self) -> Observation:
        return Observation(self.core.obs, self._received, self.core.state, self.core.t)

    def step(self, moves: np.ndarray, messages: np.ndarray) -> tuple[StepResult, np.ndarray]:
        """Apply `(B, n)` moves and send `(B, n, K)` bits; returns the step and `(B, n)` dropped flags."""
        result = self.core.step(moves)
        dropped = self.channel.transmit(messages)
        if result.finished.env_index.size and self.autoreset:
            done = np.zeros(self.num_envs, dtype=bool)
            done[result.finished.env_index] = True
            self.channel.reset(done)
        self._received = self.channel.received()
        return result, dropped
