"""Per-agent policies and where they come from: the oracle one agent at a time is the batched oracle,
task flags left at their defaults do not override a policy's own task, RUN without Controller is one line."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from bitcomm.commands.common import add_task_flags
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import ConfigError
from bitcomm.policies.agent_policies import BatchedPolicy, ControllerAgent, OracleAgent
from bitcomm.policies.evaluation import evaluate
from bitcomm.policies.reference import OraclePolicy
from bitcomm.policies.source import (
    CRITIC_INPUTS,
    POLICY_INPUTS,
    PolicySource,
    add_policy_flags,
    given_task_flags,
    resolve_task,
    source_from_args,
    sources_from_args,
)

TASKS = [
    TaskConfig(),
    TaskConfig(EnvConfig(act_fail_prob=0.2, act_delay=1), ChannelConfig(flip_prob=0.1, drop_prob=0.2, delay=2)),
    TaskConfig(
        EnvConfig(size=5, n_agents=3, observes=(2, 0, 1)), ChannelConfig(bits=5, recipients=((2, 1), (0,), (1,)))
    ),
]


@pytest.mark.parametrize("task", TASKS)
def test_oracle_agent_is_the_batched_oracle(task: TaskConfig) -> None:
    env = VecGoalExchange(task, 64, seed=5)
    batched, per_agent = OraclePolicy(task), BatchedPolicy(OracleAgent(task))
    for _ in range(30):
        obs = env.observe()
        (m1, b1), (m2, b2) = batched(obs), per_agent(obs)
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(b1, b2)
        env.step(m1, b1)
    assert evaluate(per_agent, task, 300, seed=1) == evaluate(batched, task, 300, seed=1)


class FakeController:
    """What `bitcomm.Controller` promises: `.task` and `act(planes, received, greedy)`."""

    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))

    def act(self, planes: np.ndarray, received: np.ndarray, greedy: bool = False) -> tuple[np.ndarray, np.ndarray]:
        n = planes.shape[0]
        return np.full(n, 4 if greedy else 1), received[:, 0]


def test_controller_agent_adapts_the_controller() -> None:
    agent = ControllerAgent(FakeController(), greedy=True)
    planes, received = np.zeros((3, 2, 4, 4), np.uint8), np.ones((3, 1, 4), np.uint8)
    moves, bits = agent.act(planes, received, np.zeros(3, int), np.arange(3))
    assert moves.tolist() == [4, 4, 4] and bits.dtype == np.uint8 and bits.shape == (3, 4)


def parse(argv: list[str], several: bool = False) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_task_flags(p)
    add_policy_flags(p, several=several)
    return p.parse_args(argv)


def test_only_typed_task_flags_change_the_base_task() -> None:
    base = TaskConfig(EnvConfig(size=4, max_steps=50), ChannelConfig(bits=4, delay=2))
    args = parse(["--flip-prob", "0.1", "--act-delay", "2"])
    assert given_task_flags(args) == {"flip_prob": 0.1, "act_delay": 2}
    task = resolve_task(args, base)
    assert task.env == EnvConfig(size=4, max_steps=50, act_delay=2)
    assert task.channel == ChannelConfig(bits=4, delay=2, flip_prob=0.1)
    # a typed value equal to the default still counts as typed
    assert resolve_task(parse(["--size", "10", "--bits", "7"]), base).env.size == 10
    with pytest.raises(ConfigError, match=r"^invalid size=10: RUN was trained with size=4$"):
        resolve_task(parse(["--size", "10"]), base, fixed=POLICY_INPUTS)
    # one policy network acts for every agent: a ring of 3 where each hears one sender, as in training, is playable
    assert resolve_task(parse(["--agents", "3"]), base, fixed=POLICY_INPUTS).env.n_agents == 3
    # the critics see every agent: their input shape is refused by the flag typed, not by the config's field (n_agents)
    with pytest.raises(ConfigError, match=r"^invalid agents=3: RUN was trained with agents=2$"):
        resolve_task(parse(["--agents", "3"]), base, fixed=CRITIC_INPUTS)
    # for reference policies the base is the paper's task, so the flags mean what they say
    assert PolicySource("oracle").task_from_args(parse([])) == TaskConfig()
    assert type(PolicySource("oracle").task_from_args(parse([])).env.size) is int


def test_sources() -> None:
    assert sources_from_args(parse([])) == [PolicySource("oracle")]
    assert source_from_args(parse(["--policy", "random"])).name == "random"
    several = sources_from_args(parse(["runs/a", "--policy", "oracle", "--policy", "random"], several=True))
    assert [s.label for s in several] == ["runs/a", "oracle", "random"]
    with pytest.raises(ConfigError, match="not both"):
        source_from_args(parse(["runs/a", "--policy", "oracle"]))
    with pytest.raises(ConfigError):
        PolicySource("nonsense")
    assert PolicySource.from_dict(PolicySource("run", "x", True).to_dict()) == PolicySource("run", "x", True)


def test_run_that_cannot_be_loaded_is_one_error_line() -> None:
    """A RUN that is not a run folder or checkpoint: one ConfigError naming it, not a traceback."""
    with pytest.raises(ConfigError, match="cannot load RUN 'runs/none'"):
        PolicySource("run", "runs/none").base_task()


def test_a_controller_evaluated_twice_with_one_seed_gives_one_figure_and_keeps_its_own_generator() -> None:
    """`evaluate(controller, seed=s)` samples by `s`, as `bitcomm eval --seed s` of the saved run does: a rerun notebook
    cell gives the same figure, and the controller's own sampling goes on where it was."""
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.networks import ModelConfig, PolicyNet

    task = TaskConfig(EnvConfig(size=3, max_steps=20), ChannelConfig(bits=4))
    controller = Controller(PolicyNet(task, ModelConfig()), {}, seed=7)
    own = controller.generator.get_state()
    first, again = (evaluate(controller, episodes=40, seed=3) for _ in range(2))
    assert first == again
    assert torch.equal(controller.generator.get_state(), own)
    fresh = Controller(controller.policy, {}, seed=3)  # what `Controller.load(run, seed=3)` starts with
    assert evaluate(BatchedPolicy(ControllerAgent(fresh)), task, episodes=40, seed=3) == first
