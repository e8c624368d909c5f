"""The critic's step beside the policy's (bitcomm.learn.beside): a speed-up that must change no number.

The two steps of a minibatch share no parameters and draw no random numbers, so running the critic's on a
helper thread leaves every parameter as the sequential update does, bit for bit; and a run on two torch threads
(the critic beside the policy, one thread each) is the run on one thread.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.vector import VecEnv
from bitcomm.learn.beside import critic_beside_policy
from bitcomm.learn.config import make_train_config
from bitcomm.learn.env_learner import EnvLearner
from bitcomm.learn.env_rollout import env_factory, play
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector
from bitcomm.learn.run import train
from test_env_learning import config as env_config

T = TypeVar("T")
TASK = TaskConfig(EnvConfig(size=4, max_steps=12), ChannelConfig(bits=4))


def parameters(policy: torch.nn.Module, critic: torch.nn.Module) -> dict[str, torch.Tensor]:
    nets = (("policy", policy), ("critic", critic))
    return {f"{who}.{k}": p.detach().clone() for who, net in nets for k, p in net.named_parameters()}


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def on_threads(threads: int, work: Callable[[], T]) -> T:
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return work()
    finally:
        torch.set_num_threads(before)


def grid_updates(threads: int, estimator: str) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Parameters of a fresh grid learner before and after two updates on one batch, on `threads` threads (2:
    the critic beside the policy, one thread each)."""
    cfg = make_train_config(task=TASK, estimator=estimator, num_envs=16, episodes=64)
    torch.manual_seed(0)
    learner = Learner(cfg)
    generator = torch.Generator().manual_seed(0)
    ro = Collector(TASK, 16).collect(learner.policy, np.random.SeedSequence(0), generator)
    start = parameters(learner.policy, learner.critic)
    with critic_beside_policy(learner, threads):
        assert (learner.helper is not None) == (threads == 2)
        for _ in range(2):
            learner.update(ro, generator)
    return start, parameters(learner.policy, learner.critic)


@pytest.mark.parametrize("estimator", ["improved", "standard"])
def test_the_critic_beside_the_policy_makes_the_same_update_bit_for_bit(estimator: str) -> None:
    start, alone = on_threads(1, lambda: grid_updates(1, estimator))
    _, beside = on_threads(2, lambda: grid_updates(2, estimator))
    assert same(alone, beside)
    learned = ("policy.message_logits.weight", "policy.move_logits.weight", "critic.body.0.weight")
    assert all(not torch.equal(start[k], alone[k]) for k in learned)


def test_a_wrapped_env_learner_makes_the_same_update_beside() -> None:
    def update(threads: int) -> dict[str, torch.Tensor]:
        cfg = env_config()
        vec = VecEnv(env_factory(cfg), 8)
        torch.manual_seed(0)
        learner = EnvLearner(cfg, vec.layout)
        generator = torch.Generator().manual_seed(0)
        ro = play(vec, learner.policy, np.random.SeedSequence(0), generator)
        with critic_beside_policy(learner, threads):
            learner.update(ro, generator)
        return parameters(learner.policy, learner.critic)

    assert same(on_threads(1, lambda: update(1)), on_threads(2, lambda: update(2)))


def test_threads_are_split_between_the_two_steps_and_given_back() -> None:
    learner = Learner(make_train_config(task=TASK))

    def check() -> None:
        with critic_beside_policy(learner, 4):
            assert torch.get_num_threads() == 2 and learner.helper is not None
        assert torch.get_num_threads() == 4 and learner.helper is None
        with critic_beside_policy(learner, 1):  # one thread: nothing changes
            assert torch.get_num_threads() == 4 and learner.helper is None

    on_threads(4, check)


def test_a_run_on_two_threads_is_the_run_on_one(tmp_path: Path) -> None:
    """With the critic beside the policy each step runs on one thread, so the whole run is reproduced."""
    cfg = dataclasses.replace(make_train_config(task=TASK, num_envs=16, episodes=64), checkpoint_seconds=1e9)

    def run(threads: int) -> dict[str, torch.Tensor]:
        return load_file(str(train(cfg, tmp_path / f"t{threads}", progress=False)))

    assert same(on_threads(1, lambda: run(1)), on_threads(2, lambda: run(2)))
