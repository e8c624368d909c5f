"""Whole episodes of a wrapped PettingZoo env, played by an `MlpPolicy` into `(T, B, n, ...)` tensors.

As on the grid (`rollout.py`), a batch plays B first episodes from their first step to their end, so
returns are Monte Carlo; steps after a copy's episode ended are padding (`valid` false). The team reward
of a step is the mean of the rewards of the agents present at it (so an env that gives every agent the
same reward keeps it as it is, and one whose agents leave does not count them after they left).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from bitcomm.config import slot_table
from bitcomm.envs.subproc_vector import SubprocVecEnv
from bitcomm.envs.vector import EnvLayout, VecEnv, VecStep, WrappedEnvMaker
from bitcomm.errors import bad_value
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.memory import BYTES_PER_GB, acting_bytes, available_bytes
from bitcomm.policies.mlp import MlpPolicy

HELD_COPIES = 3
"""A batch's buffers are held about this many times over at its peak: the steps kept to the episodes' end, their
copy into the batch's tensors, the update's copies of the rows it reads. Measured 2.4 (peak resident size above a
tiny run's: 8 episodes of 50 steps, 2 agents observing 100,000 floats and a state of as many: 1,156 MB for 480)."""


class EnvRollout(NamedTuple):
    """B whole episodes, time-major. `T` steps, `B` episodes, `n` agents, `D` padded observation size."""

    obs: torch.Tensor  # (T, B, n, D) float32
    received: torch.Tensor  # (T, B, n, slots, K) uint8
    state: torch.Tensor  # (T, B, Ds) float32
    alive: torch.Tensor  # (T, B, n) bool: the agent acts at this step
    actions: torch.Tensor  # (T, B, n) int64 (Discrete) or (T, B, n, A) float32 (Box), as sampled
    bits: torch.Tensor  # (T, B, n, K) uint8, as sent
    logp_action: torch.Tensor  # (T, B, n) at acting time
    logp_message: torch.Tensor  # (T, B, n)
    dropped: torch.Tensor  # (T, B, n) bool
    rewards: torch.Tensor  # (T, B) team reward: mean over the agents present
    done: torch.Tensor  # (T, B) bool: the episode ended after this step
    valid: torch.Tensor  # (T, B) bool
    length: np.ndarray  # (B,) episode lengths
    team_return: np.ndarray  # (B,) undiscounted sum of team rewards


def env_factory(cfg: EnvTrainConfig, drop_prob: float | None = None) -> WrappedEnvMaker:
    """A (picklable) maker of the wrapped env of `cfg` (with another drop probability, e.g. 1 to cut the channel)."""
    ch = cfg.channel if drop_prob is None else dataclasses.replace(cfg.channel, drop_prob=drop_prob)
    topology = ch.topology if isinstance(ch.topology, str) else [(str(s), str(r)) for s, r in ch.topology]
    return WrappedEnvMaker(
        cfg.env, cfg.env_kwargs, bits=ch.bits, delay=ch.delay, flip_prob=ch.flip_prob, drop_prob=ch.drop_prob,
        topology=topology, fixed_actions=ch.fixed_actions,
    )  # fmt: skip


def batch_seeds(seed: np.random.SeedSequence, num_envs: int) -> np.ndarray:
    """One env seed per copy (32 bits, what PettingZoo envs take), fixed by the batch's SeedSequence."""
    return seed.generate_state(num_envs)


def step_bytes(layout: EnvLayout, learning: bool = False) -> int:
    """What one copy's step adds to a batch's buffers (`EnvRollout`): observations and state in float32, messages
    received and sent in uint8, actions (int64 indices or float32 vectors), two log-probabilities, three flags;
    and, for a batch learned from (`learning`), the critic's queries about the step in the update
    (`EnvLearner.critic_values`, float32): n action baselines and, with the improved estimator, n per recipient
    rank, each reading every agent's action (one-hot for a discrete one) and a "given" flag. Those grow as n^3 times
    the actions: 20 agents with 5 actions each read 48,000 numbers a step, 6 with 4096 read 885,000 (measured: 2.0 GB
    resident for 16 episodes of 10 steps); an evaluation asks the critic nothing."""
    action = 8 if layout.discrete else 4 * layout.action_dim
    per_agent = 4 * layout.obs_dim + (layout.slots + 1) * layout.bits + action + 8 + 2
    queries = layout.n * (1 + slot_table(layout.recipients.T).shape[1]) if learning else 0
    critic = 4 * queries * layout.n * (layout.action_dim + 1)
    return layout.n * per_agent + 4 * layout.state_size + 6 + critic


def held_step_bytes(layout: EnvLayout, episodes: int, learning: bool = False) -> int:
    """What one step of `episodes` side by side costs at the batch's peak (`HELD_COPIES` times its buffers, the
    critic's queries with them where `learning`): what `play` refuses by, and what a command checks before it trains
    or evaluates."""
    return HELD_COPIES * episodes * step_bytes(layout, learning)


def too_long(
    layout: EnvLayout, episodes: int, steps: int, have: int, flag: str, tables: int = 0, learning: bool = False
) -> Exception:
    """The one line for `episodes` side by side whose buffers would outgrow `have` bytes at step `steps`, besides
    the `tables` a one-hot policy acts on at each step; the critic's queries (`learning`) are named where they are
    most of a step, as the agents' observations and state then do not say why it is large."""
    step = held_step_bytes(layout, episodes, learning) / BYTES_PER_GB
    critic = step - held_step_bytes(layout, episodes) / BYTES_PER_GB
    queries = f" ({critic:.2f} GB of it the critic's, reading every agent's action)" if critic > step / 2 else ""
    acting = f" besides {tables / BYTES_PER_GB:.2f} GB of one-hot tables it acts on" if tables else ""
    return bad_value(
        flag, episodes, f"{episodes} episodes side by side outgrow memory at step {steps:,} ({layout.n} agents "
        f"observing {layout.obs_dim:,} numbers, a state of {layout.state_size:,}: about {step:.2f} GB a step{queries}, "
        f"kept to the episodes' end{acting}; {have / BYTES_PER_GB:.1f} GB available); give fewer --{flag}, or shorter "
        "episodes (the env's own option in --env-kwargs, e.g. max_cycles)",
    )  # fmt: skip


@torch.no_grad()
def play(
    vec: VecEnv,
    policy: MlpPolicy,
    seed: np.random.SeedSequence,
    generator: torch.Generator | None,
    greedy: bool = False,
    on_step: Callable[[VecStep], object] | None = None,
    flag: str = "num-envs",
    learning: bool = False,
) -> EnvRollout:
    """Play one first episode in each of the B copies, sampling (or, `greedy`, the most likely action and
    message); actions and messages of absent agents are drawn but never sent. `on_step(step)` runs after each
    step of the copies (it may read `vec.envs`, e.g. to draw one: `bitcomm render`), and changes nothing.

    An episode's length is not known before it ends: a step whose buffers (`HELD_COPIES` times), with the tables a
    one-hot policy acts on, would outgrow the memory available when the batch began is refused with one line naming
    `flag`, the option that set B (with the critic's queries about it where the batch is for `learning`)."""
    B = vec.num_envs
    have = available_bytes()
    layout = vec.layout
    tables = B * acting_bytes(layout.n, layout.bits, layout.slots) if policy.head.name == "onehot" else 0
    per_step = held_step_bytes(layout, B, learning)
    ob = vec.reset(batch_seeds(seed, B))
    dist = policy.actions
    steps: list[tuple[np.ndarray, ...]] = []
    valid_now = np.ones(B, bool)
    length, team_return = np.zeros(B, np.int64), np.zeros(B)
    while valid_now.any():
        if (len(steps) + 1) * per_step + tables > have:
            raise too_long(layout, B, len(steps) + 1, have, flag, tables, learning)
        obs, received = torch.from_numpy(ob.obs), torch.from_numpy(ob.received)
        act_out, msg_logits = policy(obs, received)
        actions, bits = policy.draw(act_out, msg_logits, greedy, generator)
        logp_a, logp_m = dist.log_prob(act_out, actions), policy.head.log_prob(msg_logits, bits)
        a_np, bits_np = actions.numpy(), bits.numpy()
        st = vec.step(a_np, bits_np)
        if on_step is not None:
            on_step(st)
        alive = ob.alive & valid_now[:, None]
        present = alive.sum(1)
        team = np.where(present > 0, (st.rewards * alive).sum(1) / np.maximum(present, 1), 0.0).astype(np.float32)
        team = np.where(valid_now, team, 0.0).astype(np.float32)
        steps.append(
            (ob.obs, ob.received, ob.state, alive, a_np, bits_np, logp_a.numpy(), logp_m.numpy(),
             st.dropped & alive, team, st.ended & valid_now, valid_now.copy())
        )  # fmt: skip
        length += valid_now
        team_return += team
        valid_now = valid_now & ~st.ended
        ob = st.next
    c = [torch.from_numpy(np.stack(x)) for x in zip(*steps, strict=True)]
    return EnvRollout(c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10], c[11], length, team_return)


def make_vec(cfg: EnvTrainConfig, num_envs: int, drop_prob: float | None = None, workers: int = 0) -> VecEnv:
    """B copies of the wrapped env of `cfg`: in this process (`workers` 0), or split over `workers` processes
    (`SubprocVecEnv`: the same episodes, for slow envs). Close it (`with`) when done."""
    make = env_factory(cfg, drop_prob)
    return SubprocVecEnv(make, num_envs, workers, cfg.env) if workers else VecEnv(make, num_envs)
