"""The held-out evaluation a sync run makes every `TrainConfig.held_out_every` episodes (model selection).

Greedy play can move along a run while sampled play stays level: a few goal pairs whose most likely codes
collide stall an episode to its step limit, and which pairs do changes from one update to the next
(docs/tuning.md, sessions 27-29). A run that evaluates keeps the checkpoint that played a fixed held-out
episode set best (`checkpoints/best.json`), as Stable-Baselines3's `EvalCallback` keeps `best_model`. The
policy plays it through `bitcomm.Controller`, as `bitcomm eval` and a deployed robot do, on a copy of its
weights with a generator of its own: the run's random streams are untouched, so a run with evaluations
trains exactly as one without.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bitcomm.learn.config import TrainConfig
from bitcomm.policies.networks import PolicyNet

HELD_OUT_COLUMN = "eval/episode_length"
"""The log column of a held-out evaluation (`HeldOut`), empty in the rows of batches without one."""


@dataclass(frozen=True)
class HeldOut:
    """A held-out evaluation during training: `play()` returns the mean episode length of a fixed episode set
    no training batch plays, every `every` episodes and at the end (`TrainConfig.held_out_every`)."""

    every: int
    play: Callable[[], float]

    def due(self, before: int, after: int, budget: int) -> bool:
        """Whether the batch that took the run from `before` to `after` episodes crossed an evaluation point."""
        return after // self.every > before // self.every or after >= budget


HELD_OUT_KEY = 2**32
"""The spawn key of the held-out set's seed under the run's seed: batch k plays `SeedSequence(seed,
spawn_key=(k,))`, and no run plays 2^32 batches."""


def held_out_seed(seed: int) -> int:
    """The seed of run `seed`'s held-out episode set (an `evaluate` seed): one no training batch plays, and
    not a small number a user would pick for `bitcomm eval --seed`."""
    return int(np.random.SeedSequence(seed, spawn_key=(HELD_OUT_KEY,)).generate_state(1)[0])


def held_out(cfg: TrainConfig, policy: PolicyNet) -> HeldOut | None:
    """The held-out evaluation of `policy` under `cfg` (None when `held_out_every` is 0): the mean episode length of
    `held_out_episodes` episodes of the full task (not `train_max_steps`'s), greedy or sampled (`held_out_greedy`)."""
    if not cfg.held_out_every:
        return None
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate_controller

    seed = held_out_seed(cfg.seed)
    config = cfg.to_dict()

    def play() -> float:
        controller = Controller(copy.deepcopy(policy), config, seed=seed)  # eval mode on the copy alone
        return evaluate_controller(
            controller, cfg.held_out_episodes, seed, cfg.held_out_greedy, cfg.task
        ).mean_episode_length

    return HeldOut(cfg.held_out_every, play)
