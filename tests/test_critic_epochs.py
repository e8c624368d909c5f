"""The critics' passes over a batch (`critic_epochs`): the critics step in the first passes of an update only.

Every advantage of a batch is computed before its first step, so the critics' passes cannot change the policy's
update of that batch: only the next batch's baselines. Fewer passes therefore leave the policy's steps as they were
and the critics where the first passes put them, and 0 keeps every pass.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.vector import VecEnv
from bitcomm.errors import ConfigError
from bitcomm.learn.config import make_train_config
from bitcomm.learn.env_learner import EnvLearner
from bitcomm.learn.env_rollout import env_factory, play
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector
from test_beside import parameters, same
from test_env_learning import config as env_config

TASK = TaskConfig(EnvConfig(size=4, max_steps=12), ChannelConfig(bits=4))


def split(params: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """`parameters(policy, critic)` as the policy's and the critics'."""
    return tuple({k: v for k, v in params.items() if k.startswith(who)} for who in ("policy.", "critic."))  # type: ignore[return-value]


def grid_update(estimator: str, epochs: int, critic_epochs: int) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """A fresh grid learner's parameters after one update of `epochs` passes (4 minibatches each) on one batch."""
    cfg = make_train_config(
        task=TASK, estimator=estimator, num_envs=16, episodes=64, epochs=epochs, critic_epochs=critic_epochs
    )
    torch.manual_seed(0)
    learner = Learner(cfg)
    generator = torch.Generator().manual_seed(0)
    ro = Collector(TASK, 16).collect(learner.policy, np.random.SeedSequence(0), generator)
    stats = learner.update(ro, generator)
    return parameters(learner.policy, learner.critic), stats


def env_update(epochs: int, critic_epochs: int) -> dict[str, torch.Tensor]:
    cfg = dataclasses.replace(env_config(), epochs=epochs, critic_epochs=critic_epochs)
    vec = VecEnv(env_factory(cfg), 8)
    torch.manual_seed(0)
    learner = EnvLearner(cfg, vec.layout)
    generator = torch.Generator().manual_seed(0)
    learner.update(play(vec, learner.policy, np.random.SeedSequence(0), generator), generator)
    return parameters(learner.policy, learner.critic)


@pytest.mark.parametrize("estimator", ["improved", "standard"])
def test_the_critics_step_in_the_first_passes_and_the_policys_steps_are_unchanged(estimator: str) -> None:
    policy_every, critic_every = split(grid_update(estimator, 4, 0)[0])
    _, critic_first_pass = split(grid_update(estimator, 1, 0)[0])  # an update of one pass
    by_passes = {k: split(grid_update(estimator, 4, k)[0]) for k in (1, 2, 4)}
    assert all(same(policy, policy_every) for policy, _ in by_passes.values())
    assert same(by_passes[4][1], critic_every)  # 0: every pass
    assert same(by_passes[1][1], critic_first_pass)
    assert not same(by_passes[2][1], critic_first_pass) and not same(by_passes[2][1], critic_every)


def test_the_critics_loss_is_logged_over_the_steps_they_made() -> None:
    _, stats = grid_update("improved", 2, 1)
    assert np.isfinite(stats["losses/value"])
    assert stats["losses/value"] == pytest.approx(grid_update("improved", 1, 0)[1]["losses/value"])


def test_a_wrapped_envs_critic_steps_in_the_first_passes_alone() -> None:
    policy_every, critic_every = split(env_update(4, 0))
    policy, critic = split(env_update(4, 1))
    assert same(policy, policy_every) and not same(critic, critic_every)
    assert same(critic, split(env_update(1, 0))[1])


@pytest.mark.parametrize("value", [5, -1, 1.5, True])
def test_critic_epochs_outside_zero_to_epochs_is_one_line_naming_both(value: object) -> None:
    with pytest.raises(ConfigError, match=r"^invalid critic-epochs=.*: must be an integer in \[0, epochs \(4\)\]"):
        make_train_config(task=TASK, epochs=4, critic_epochs=value)
    with pytest.raises(ConfigError, match=r"^invalid critic-epochs=.*epochs \(4\)"):
        dataclasses.replace(env_config(), epochs=4, critic_epochs=value)
