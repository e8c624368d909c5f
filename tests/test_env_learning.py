"""Learning on any PettingZoo env wrapped in bitcomm's channel (SPEC sections 4, 7 and 8; issue 18).

A test-local env, `SignalEnv`, has a speaker that sees a random bit and a listener that is rewarded for
acting on it one step later: only the channel can carry it.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import errno
import json
import os
import re
import signal
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from bitcomm.cli import main
from bitcomm.envs.vector import EnvLayout, VecEnv, flat_row, inner_action
from bitcomm.errors import ConfigError
from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
from bitcomm.learn.env_eval import evaluate_env
from bitcomm.learn.env_learner import EnvLearner
from bitcomm.learn.env_rollout import EnvRollout, env_factory, play
from bitcomm.learn.env_run import train_env
from bitcomm.learn.estimators import Advantages, discounted_returns
from bitcomm.learn.run_folder import RESUMES

SPEC = f"{__name__}:SignalEnv"


class SignalEnv(ParallelEnv):
    """Speaker (obs: the bit; 1 action) and listener (obs: 3 numbers, no bit; 2 actions). From step 1 on, the
    listener earns 1 when its action equals the bit. `steps` steps; with `speaker_leaves` the speaker
    terminates after step 0; with `handover` the speaker alone plays step 0 and the listener joins as it
    leaves (its message on the wire between them); with `box`, Box actions (speaker 1 number, listener 2; the
    listener's action is 1 when its first number is positive). No `state()`: the critic reads the concatenated
    observations."""

    metadata = {"name": "signal_v0"}

    def __init__(self, steps: int = 2, speaker_leaves: bool = False, box: bool = False, handover: bool = False) -> None:
        self.possible_agents = ["speaker", "listener"]
        self.agents: list[str] = []
        self.steps, self.speaker_leaves, self.handover = steps, speaker_leaves or handover, handover
        self._obs = {"speaker": spaces.Box(0, 1, (1,), np.float32), "listener": spaces.Box(0, 1, (3,), np.float32)}
        self._act: dict[str, spaces.Space] = {"speaker": spaces.Discrete(1), "listener": spaces.Discrete(2)}
        if box:
            self._act = {a: spaces.Box(-1, 1, (k,), np.float32) for a, k in (("speaker", 1), ("listener", 2))}
        self.box = box

    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self._act[agent]

    def _observe(self) -> dict[str, np.ndarray]:
        return {
            "speaker": np.array([self.bit], np.float32),
            "listener": np.array([0.5, 0.5, self.t / self.steps], np.float32),
        }

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.bit, self.t = int(np.random.default_rng(seed).integers(2)), 0
        self.agents = ["speaker"] if self.handover else list(self.possible_agents)
        obs = self._observe()
        return {a: obs[a] for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        act = actions.get("listener")
        if self.box and act is not None:
            assert np.all(np.abs(act) <= 1), act  # clipped to the bounds before it reaches the env
        r = float(act is not None and self.t >= 1 and int(act[0] > 0 if self.box else act) == self.bit)
        self.t += 1
        acting = list(self.agents)
        trunc = {a: self.t >= self.steps for a in acting}
        term = {a: a == "speaker" and self.speaker_leaves for a in acting}
        self.agents = [a for a in acting if not (trunc[a] or term[a])]
        if self.handover and self.t == 1 and self.t < self.steps:
            self.agents.append("listener")
        obs = self._observe()
        return (
            {a: obs[a] for a in {*acting, *self.agents}},
            {a: r for a in acting},
            term,
            trunc,
            {a: {} for a in acting},
        )


SPACES = {
    "box": spaces.Box(-1, 1, (3,), np.float32),
    "image": spaces.Box(0, 255, (2, 2, 3), np.uint8),
    "discrete from 1": spaces.Discrete(3, start=1),
    "discrete from -1": spaces.Discrete(3, start=-1),
    "multidiscrete": spaces.MultiDiscrete([2, 3]),
    "multibinary": spaces.MultiBinary(2),
    "dict": spaces.Dict(cell=spaces.Discrete(2), near=spaces.Box(-1, 1, (2,), np.float32)),
    "box 2x2": spaces.Box(-1, 1, (2, 2), np.float64),
    "sequence": spaces.Sequence(spaces.Discrete(2)),
    "text": spaces.Text(5, charset="abc"),
    "multidiscrete 100x100": spaces.MultiDiscrete([100, 100]),
    "multibinary 12": spaces.MultiBinary(12),  # 4096 combinations, the most learning takes
}


class SpacesEnv(ParallelEnv):
    """Agents a and b with the observation and action spaces named in `SPACES`; observations are seeded draws
    from the space, and every action received is checked to be in its space and kept in `received`."""

    metadata = {"name": "spaces_v0"}

    def __init__(
        self, obs: str = "box", act: str = "discrete from 1", agents: list[Any] | None = None, state: str = "none"
    ) -> None:
        self.possible_agents, self.agents = agents or ["a", "b"], []
        if state == "state_space":  # a global state, PettingZoo's way
            self.state_space = spaces.Box(0, 1, (4,), np.float32)
            self.state = lambda: np.full(4, 0.5, np.float32)  # type: ignore[method-assign]
        elif state == "dict":  # what PettingZoo's classic envs keep under that name: state() raises TypeError
            self.state = {"round": 0}  # type: ignore[assignment,method-assign]
        self._obs, self._act = copy.deepcopy(SPACES[obs]), SPACES[act]  # each copy draws from its own generator
        self.shown: list[dict[str, Any]] = []  # the observations of every reset and step
        self.received: list[dict[str, Any]] = []

    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs

    def action_space(self, agent: str) -> spaces.Space:
        return self._act

    def _observe(self) -> dict[str, Any]:
        self.shown.append({a: self._obs.sample() for a in self.possible_agents})
        return self.shown[-1]

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self._obs.seed(seed)
        self.agents, self.shown, self.received = list(self.possible_agents), [], []
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        for a, act in actions.items():
            assert self._act.contains(act), (a, act, self._act)
        self.received.append(actions)
        done = len(self.received) >= 2
        self.agents = [] if done else list(self.possible_agents)
        obs = self._observe()
        return obs, dict.fromkeys(obs, 0.0), dict.fromkeys(obs, False), dict.fromkeys(obs, done), {a: {} for a in obs}


class MixedActionsEnv(SignalEnv):
    """SignalEnv whose listener acts in a Box while the speaker's action is Discrete."""

    def __init__(self) -> None:
        super().__init__()
        self._act = {"speaker": spaces.Discrete(1), "listener": spaces.Box(-1, 1, (2,), np.float32)}


class ReviveEnv(SignalEnv):
    """SignalEnv of 4 steps whose speaker terminates at each step it plays and is listed again two steps later (an
    agent that respawns): it plays steps 0 and 2."""

    def __init__(self) -> None:
        super().__init__(steps=4, speaker_leaves=True)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        obs, rewards, term, trunc, info = super().step(actions)
        if self.t == 2:
            self.agents.append("speaker")
            obs["speaker"] = self._observe()["speaker"]
        return obs, rewards, term, trunc, info


class NobodyEnv(SignalEnv):
    """SignalEnv whose reset lists no agent."""

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        super().reset(seed, options)
        self.agents = []
        return {}, {}


class NamedInResetEnv(SignalEnv):
    """SignalEnv that names its agents only in reset."""

    def __init__(self) -> None:
        super().__init__()
        del self.possible_agents

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.possible_agents = ["speaker", "listener"]
        return super().reset(seed, options)


class OddRewardEnv(SignalEnv):
    """SignalEnv whose rewards become `reward` (as given: NaN, inf, None, a string...; "raise": its step raises, as
    an env's own bug would; "interrupt": a KeyboardInterrupt comes during its step; "array": `np.array([1.0])`;
    "missing": the speaker's is left out) from its `from_reset`-th reset on (each copy counts its own; the first
    copy is also reset once when its spaces are read)."""

    def __init__(self, reward: Any = "nan", from_reset: int = 1) -> None:
        super().__init__()
        self.reward, self.from_reset, self.resets = {"nan": np.nan, "inf": np.inf}.get(reward, reward), from_reset, 0

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.resets += 1
        return super().reset(seed, options)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        obs, rewards, term, trunc, infos = super().step(actions)
        if self.resets >= self.from_reset:
            if self.reward == "raise":
                raise ZeroDivisionError("the env's own bug")
            if self.reward == "interrupt":  # Ctrl-C a second time while the batch's episodes go on
                raise KeyboardInterrupt
            if self.reward == "missing":
                rewards = {a: r for a, r in rewards.items() if a != "speaker"}
            else:
                rewards = dict.fromkeys(rewards, np.array([1.0]) if self.reward == "array" else self.reward)
        return obs, rewards, term, trunc, infos


class OddObservationEnv(SignalEnv):
    """SignalEnv whose listener's observation at its second step is `odd`: "nan" or "inf" in one number,
    "longer" (4 numbers for a space of 3), "scalar" (one number, which numpy would broadcast over 3), "missing"
    (no observation for it while it is listed), "state nan" (a `state_space` whose `state()` gives NaN), "state
    longer" (a `state()` of 3 numbers after 2), "state dict" or "state none" (a `state()` that is no array)."""

    def __init__(self, odd: str = "nan") -> None:
        super().__init__(steps=3)
        self.odd = odd
        if odd.startswith("state"):
            self.state_space = spaces.Box(0, 1, (2,), np.float32)

    def state(self) -> Any:
        if self.odd == "state longer":
            return np.full(3 if self.t >= 1 else 2, 0.5, np.float32)
        if self.odd in ("state dict", "state none"):
            return {"x": 0.5} if self.odd == "state dict" else None
        return np.array([0.5, np.nan if self.t >= 1 else 0.5], np.float32)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        obs, rewards, term, trunc, infos = super().step(actions)
        if self.t == 1:
            odd = {"nan": np.array([0.5, np.nan, 0.5], np.float32), "inf": np.array([0.5, np.inf, 0.5], np.float32),
                   "longer": np.zeros(4, np.float32), "scalar": np.float32(0.5)}  # fmt: skip
            if self.odd in odd:
                obs["listener"] = odd[self.odd]
            elif self.odd == "missing":
                del obs["listener"]
        return obs, rewards, term, trunc, infos


class CountedEnv(SignalEnv):
    """SignalEnv that counts the copies made and closed (an env may hold a window, files or a process)."""

    made: list[CountedEnv] = []

    def __init__(self) -> None:
        super().__init__()
        self.closed = False
        CountedEnv.made.append(self)

    def close(self) -> None:
        self.closed = True


def config(**kw: Any) -> EnvTrainConfig:
    channel = EnvChannelConfig(**kw.pop("channel", {"bits": 2}))
    base: dict[str, Any] = dict(env=SPEC, num_envs=8, episodes=16, hidden=(32,), checkpoint_seconds=1e9)
    return EnvTrainConfig(**{**base, "channel": channel, **kw})


# ---------------------------------------------------------------------------------------------- arrays
def test_vector_env_and_rollout_shapes() -> None:
    cfg = config(env_kwargs={"steps": 3, "speaker_leaves": True})
    vec = VecEnv(env_factory(cfg), 4)
    L = vec.layout
    assert (L.n, L.obs_sizes, L.obs_dim, L.action_sizes, L.slots, L.bits) == (2, (1, 3), 3, (1, 2), 1, 2)
    assert not L.has_state and L.state_size == 2 * 3
    torch.manual_seed(0)
    learner = EnvLearner(cfg, L)
    ro = play(vec, learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    T, B = 3, 4
    assert ro.obs.shape == (T, B, 2, 3) and ro.received.shape == (T, B, 2, 1, 2) and ro.state.shape == (T, B, 6)
    assert ro.actions.shape == ro.alive.shape == ro.logp_action.shape == ro.dropped.shape == (T, B, 2)
    assert ro.bits.shape == (T, B, 2, 2) and ro.rewards.shape == ro.valid.shape == (T, B)
    assert ro.valid.all() and ro.done[-1].all() and not ro.done[:-1].any()
    assert ro.alive[0].all() and not ro.alive[1:, :, 0].any() and ro.alive[:, :, 1].all()  # the speaker left
    assert (ro.obs[:, :, 0, 1:] == 0).all()  # padding beyond the speaker's one number
    assert torch.equal(ro.state[0], ro.obs[0].flatten(1))  # no state(): the padded observations
    assert (ro.actions[:, :, 0] == 0).all()  # the speaker has one action: the rest are masked
    np.testing.assert_array_equal(ro.length, [3] * B)


def test_an_agent_that_joins_as_the_others_leave_plays_on() -> None:
    """The episode ends when no listed agent plays on, not when every agent that acted has finished: here the
    speaker's last step is the listener's first."""
    vec = VecEnv(env_factory(config(env_kwargs={"steps": 3, "handover": True})), 4)
    torch.manual_seed(0)
    ro = play(vec, EnvLearner(config(), vec.layout).policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    np.testing.assert_array_equal(ro.length, [3] * 4)
    assert ro.alive[0, :, 0].all() and not ro.alive[0, :, 1].any()  # step 0: the speaker alone
    assert ro.alive[1:, :, 1].all() and not ro.alive[1:, :, 0].any()  # then the listener alone
    assert ro.done[-1].all() and not ro.done[:-1].any()


def test_an_agent_listed_again_after_it_left_plays_again() -> None:
    """PettingZoo lets an env list an agent again after it terminated (one that respawns): it acts and sends from
    the step it is listed again, and is learned from on the steps it plays, as an agent that joins late is."""
    cfg = config(env=f"{__name__}:ReviveEnv")
    vec = VecEnv(env_factory(cfg), 4)
    torch.manual_seed(0)
    learner = EnvLearner(cfg, vec.layout)
    ro = play(vec, learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    np.testing.assert_array_equal(ro.length, [4] * 4)
    assert ro.alive[:, :, 0].T.tolist() == [[True, False, True, False]] * 4
    assert ro.alive[:, :, 1].all()
    assert torch.isfinite(torch.tensor(list(learner.update(ro).values()))).all()


def test_box_actions_are_gaussian_and_padded() -> None:
    cfg = config(env_kwargs={"box": True})
    vec = VecEnv(env_factory(cfg), 4)
    assert not vec.layout.discrete and vec.layout.action_sizes == (1, 2)
    torch.manual_seed(0)
    learner = EnvLearner(cfg, vec.layout)
    ro = play(vec, learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))
    assert ro.actions.shape == (2, 4, 2, 2) and (ro.actions[:, :, 0, 1] == 0).all()  # the speaker's padding
    dist = learner.policy.actions
    out, _ = learner.policy(ro.obs[0], ro.received[0])
    torch.testing.assert_close(dist.log_prob(out, ro.actions[0]), ro.logp_action[0])
    assert torch.isfinite(torch.tensor(list(learner.update(ro).values()))).all()


@pytest.mark.parametrize("act", ["discrete from 1", "discrete from -1", "multidiscrete", "multibinary", "box 2x2"])
def test_actions_reach_the_env_in_its_own_space(act: str) -> None:
    """A Discrete action is the policy's index shifted by the space's start; a MultiDiscrete or MultiBinary one is
    the combination the index numbers (C order); a Box action has its shape and dtype."""
    vec = VecEnv(env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs={"act": act})), 2)
    torch.manual_seed(0)
    ro = play(vec, EnvLearner(config(), vec.layout).policy, np.random.SeedSequence(0), None)
    space = SPACES[act]
    for b, env in enumerate(vec.envs):
        for t, actions in enumerate(env.inner.received):  # every one was in the space (SpacesEnv checks)
            for i, a in enumerate("ab"):
                if isinstance(space, spaces.Discrete):
                    assert actions[a] == int(ro.actions[t, b, i]) + space.start
                elif isinstance(space, (spaces.MultiDiscrete, spaces.MultiBinary)):
                    sizes = space.nvec if isinstance(space, spaces.MultiDiscrete) else [2] * space.n
                    assert actions[a].tolist() == list(np.unravel_index(int(ro.actions[t, b, i]), sizes))
                else:  # clipped to the bounds on the way
                    want = ro.actions[t, b, i].clamp(-1, 1).numpy()
                    np.testing.assert_allclose(actions[a].ravel(), want, rtol=1e-6)


@pytest.mark.parametrize("obs", ["image", "discrete from 1", "multidiscrete", "multibinary", "dict", "text"])
def test_observations_of_any_flattenable_space_are_flattened(obs: str) -> None:
    """Box values as they are; Discrete and MultiDiscrete one-hot, MultiBinary bits, Dict concatenated, Text as
    each character's index in its charset (padded with the charset's size)."""
    vec = VecEnv(env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs={"obs": obs})), 1)
    space = SPACES[obs]
    assert vec.layout.obs_sizes == (spaces.flatdim(space),) * 2
    torch.manual_seed(0)
    ro = play(vec, EnvLearner(config(), vec.layout).policy, np.random.SeedSequence(0), None)
    shown = vec.envs[0].inner.shown
    for t in range(2):
        for i, a in enumerate("ab"):
            want = spaces.flatten(space, shown[t][a]).astype(np.float32)
            np.testing.assert_array_equal(ro.obs[t, 0, i].numpy(), want)


@pytest.mark.parametrize(
    ("kwargs", "names"),
    [
        ({"act": "multidiscrete 100x100"}, "action_space('a')=MultiDiscrete([100 100]): learning acts on its 10000"),
        ({"act": "dict"}, "action_space('a')=Dict('cell': Discrete(2), 'near': Box(-1.0, 1.0, (2,), float32)): le"),
        ({"obs": "sequence"}, "observation_space('a')=Sequence(Discrete(2), stack=False): learning needs one"),
    ],
)
def test_spaces_learning_cannot_use_are_one_line(kwargs: dict[str, str], names: str) -> None:
    make = env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs=kwargs))
    make().reset(seed=0)  # the wrapper carries them
    with pytest.raises(ConfigError) as err:
        VecEnv(make, 1)
    assert "\n" not in str(err.value) and names in str(err.value), err.value


def test_agents_whose_actions_mix_box_and_discrete_are_one_line_naming_both() -> None:
    """The line named the env's class alone: which agent's space was the odd one, and what would do, were left out."""
    make = env_factory(config(env=f"{__name__}:MixedActionsEnv"))
    with pytest.raises(ConfigError) as err:
        VecEnv(make, 1)
    assert str(err.value) == (
        "invalid action_space('listener')=Box(-1.0, 1.0, (2,), float32): is a Box while action_space('speaker') is "
        "Discrete(1): learning needs every agent's actions Box, or every agent's Discrete, MultiDiscrete or MultiBinary"
    )


@pytest.mark.parametrize(("state", "size"), [("state_space", 4), ("none", 2 * 3), ("dict", 2 * 3)])
def test_the_critic_reads_the_env_state_where_it_has_a_state_space(state: str, size: int) -> None:
    """Else the concatenated padded observations (two agents, three numbers each)."""
    vec = VecEnv(env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs={"state": state})), 2)
    assert vec.layout.has_state == (state == "state_space") and vec.layout.state_size == size
    torch.manual_seed(0)
    ro = play(vec, EnvLearner(config(), vec.layout).policy, np.random.SeedSequence(0), None)
    assert ro.state.shape == (2, 2, size) and (ro.state == 0.5).all() == (state == "state_space")


def test_json_agent_names_reach_an_env_whose_agents_are_not_strings() -> None:
    channel = {"bits": 2, "topology": [["0", "1"]], "fixed_actions": {"1": 2}}
    env = env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs={"agents": [0, 1]}, channel=channel))()
    assert env.recipients.tolist() == [[False, True], [False, False]] and env.fixed_actions == {1: 2}


def test_a_topology_naming_an_agent_by_its_int_says_to_write_it_as_json_does() -> None:
    """The line said "agent-name pairs" to a user who had named agent 0 by its name, 0."""
    with pytest.raises(ConfigError, match=re.escape('each name a string as JSON writes it ("0" for an agent 0)')):
        EnvChannelConfig(topology=[(0, 1)])  # type: ignore[list-item]


def test_a_multidiscrete_action_is_numbered_by_its_combinations() -> None:
    space = spaces.MultiDiscrete([[2, 3], [1, 2]], start=[[1, -1], [0, 5]])
    actions = [inner_action(space, np.int64(i)) for i in range(12)]
    assert all(space.contains(x) for x in actions) and len({x.tobytes() for x in actions}) == 12
    assert actions[0].tolist() == [[1, -1], [0, 5]] and actions[11].tolist() == [[2, 1], [0, 6]]


def test_a_box_action_at_its_bounds_is_in_the_space_whatever_its_dtype() -> None:
    """The learner clips in float32; a float64 bound such as 0.1 has no float32 twin, and the env gets its own."""
    space = spaces.Box(np.array([-0.1, 0.0]), np.array([0.1, 0.3]), dtype=np.float64)
    low, high = space.low[None].astype(np.float32), space.high[None].astype(np.float32)  # as EnvLayout.of reads them
    layout = EnvLayout(
        ("a",), (1,), 1, 1, 1, False, (2,), low, high, 2, False, np.zeros(1, bool), np.zeros((1, 1), bool)
    )
    for sample in ([5.0, 5.0], [-5.0, -5.0]):
        action = inner_action(space, layout.clip(np.array([sample], np.float32))[0])
        assert action.dtype == np.float64 and space.contains(action), action
    scalar = spaces.Box(0, 5, (), np.int64)  # the env gets an array of its shape (), as gymnasium's own sample()
    assert isinstance(inner_action(scalar, np.array([7.0], np.float32)), np.ndarray)


def test_an_integer_box_gets_the_nearest_integer_of_the_learners_action() -> None:
    """A Gaussian's sample reached an integer Box cast toward zero (2.7 -> 2, -0.6 -> 0): every action but the
    nearest, and half of the range for small values. It is rounded, then clipped to the space."""
    space = spaces.Box(-3, 3, (4,), np.int64)
    action = inner_action(space, np.array([2.7, -0.6, -2.5, 9.0], np.float32))
    assert action.dtype == np.int64 and action.tolist() == [3, -1, -2, 3] and space.contains(action)


def test_rollouts_are_seeded() -> None:
    cfg = config()
    vec = VecEnv(env_factory(cfg), 4)
    torch.manual_seed(0)
    policy = EnvLearner(cfg, vec.layout).policy
    a, b = (play(vec, policy, np.random.SeedSequence(3), torch.Generator().manual_seed(1)) for _ in range(2))
    assert all(torch.equal(x, y) for x, y in zip(a[:12], b[:12], strict=True))


# ---------------------------------------------------------------------------------------------- credit
class StubCritic(torch.nn.Module):
    """V = 1000 t + 100 (viewpoint + 1) + sum_k given_k 2^k: every query tells which it was. As `MlpCritic`, it
    takes each state once for its consecutive queries."""

    with_message = False

    def forward(self, state: torch.Tensor, viewpoint: torch.Tensor, actions: Any, given: torch.Tensor, _: Any) -> Any:
        t = state[:, 0].repeat_interleave(len(viewpoint) // len(state))
        return 1000 * t + 100 * (viewpoint + 1) + (given.float() * torch.tensor([1.0, 2.0, 4.0])).sum(1)


CREDIT_T = 5
"""Steps of the hand-computed credit cases: agent 0 talks to agents 1 and 2 with delay 2, gamma 0.5."""
CREDIT_Q = [1 + 0.5 * 2 + 0.25 * 3 + 0.125 * 4 + 0.0625 * 5, 2 + 1.5 + 1 + 0.625, 3 + 2 + 1.25, 4 + 2.5, 5.0]
"""Their returns from rewards 1, 2, 3, 4, 5."""


def stub_value(t: int, viewpoint: int, given: list[int]) -> float:
    """`StubCritic`'s value at step t from agent `viewpoint`'s view, given the actions of the agents `given`."""
    return 1000 * t + 100 * (viewpoint + 1) + sum(2**k for k in given)


class StubCriticV1(StubCritic):
    """`StubCritic` that also reads the judged agent's inbox (one 1-bit slot): + 50 when it holds a 1."""

    with_message = True

    def forward(self, state: torch.Tensor, viewpoint: torch.Tensor, actions: Any, given: torch.Tensor, rec: Any) -> Any:
        return super().forward(state, viewpoint, actions, given, None) + 50 * rec[:, 0, 0].float()


def credit_by_hand(
    alive: torch.Tensor, dropped: torch.Tensor, estimator: str = "improved", received: torch.Tensor | None = None
) -> Advantages:
    """The estimator's advantages on the hand case (agents a, b, c; `alive` and `dropped` (T, 1, 3); `received`
    (T, 1, 3) the bit each agent's inbox holds, read by the standard estimator's V1)."""
    n, T, d = 3, CREDIT_T, 2
    rec = np.zeros((n, n), bool)
    rec[0, 1] = rec[0, 2] = True
    layout = EnvLayout(
        ("a", "b", "c"), (1, 1, 1), 1, 1, d, True, (2, 2, 2), np.zeros((n, 2)), np.zeros((n, 2)), 1, True,
        np.zeros(n, bool), rec,
    )  # fmt: skip
    cfg = config(estimator=estimator, gamma=0.5, adv_norm=False, channel={"bits": 1, "delay": d})
    learner = EnvLearner(cfg, layout)
    learner.critic = StubCriticV1() if estimator == "standard" else StubCritic()  # type: ignore[assignment]
    inbox = torch.zeros(T, 1, n, dtype=torch.uint8) if received is None else received.to(torch.uint8)
    rewards = torch.tensor([[1.0], [2.0], [3.0], [4.0], [5.0]])
    done, valid = torch.zeros(T, 1, dtype=torch.bool), torch.ones(T, 1, dtype=torch.bool)
    done[-1] = True
    z = torch.zeros(T, 1, n)
    ro = EnvRollout(
        z[..., None], inbox[..., None, None], torch.arange(T).float().view(T, 1, 1), alive,
        torch.zeros(T, 1, n, dtype=torch.long), torch.zeros(T, 1, n, 1, dtype=torch.uint8), z, z, dropped, rewards,
        done, valid, np.array([T]), np.array([15.0]),
    )  # fmt: skip
    adv = learner.advantages(ro)
    torch.testing.assert_close(adv.returns[:, 0], torch.tensor(CREDIT_Q))
    return adv


def test_multi_recipient_credit_by_hand() -> None:
    """Agent 0 talks to agents 1 and 2, delay 2. Its message at t=0 is credited by both recipients at t=2,
    at t=1 only by agent 1 (agent 2 is absent at t=3), at t=2 not at all (dropped), later never (arrives
    after the end). Agents 1 and 2 talk to nobody: their messages get 0."""
    q, v = CREDIT_Q, stub_value
    alive = torch.ones(CREDIT_T, 1, 3, dtype=torch.bool)
    alive[3, 0, 2] = False
    dropped = torch.zeros(CREDIT_T, 1, 3, dtype=torch.bool)
    dropped[2, 0, 0] = True
    adv = credit_by_hand(alive, dropped)
    # the message baseline of sender 0 gives only agent 0's action (its recipients' are masked)
    m0 = [0.25 * ((q[2] - v(2, 1, [0])) + (q[2] - v(2, 2, [0]))), 0.25 * (q[3] - v(3, 1, [0])), 0.0, 0.0, 0.0]
    torch.testing.assert_close(adv.message[:, 0, 0], torch.tensor(m0))
    assert (adv.message[:, 0, 1:] == 0).all()
    # action baselines: every other present agent's action given
    assert adv.action[3, 0, 0].item() == pytest.approx(q[3] - v(3, 0, [1]))
    assert adv.action[1, 0, 2].item() == pytest.approx(q[1] - v(1, 2, [0, 1]))
    assert adv.action[3, 0, 2].item() == 0.0  # agent 2 is absent at t=3


def test_a_message_sent_before_its_sender_left_is_credited_on_arrival_by_hand() -> None:
    """Agent 0 talks to agents 1 and 2, delay 2, and leaves after step 1: its messages of steps 0 and 1 are in
    flight when it leaves, reach their recipients at steps 2 and 3 (BitChannel delivers them) and are credited
    there. The baseline at arrival never gives the absent sender's action; it sends nothing after it left (no
    credit, no log-probability). Agent 2 is truncated after step 2 while agent 1 plays on: at step 3 only
    agent 1 credits agent 0's last message."""
    q, v = CREDIT_Q, stub_value
    alive = torch.ones(CREDIT_T, 1, 3, dtype=torch.bool)
    alive[2:, 0, 0] = False  # agent 0 acts at steps 0 and 1 only
    alive[3:, 0, 2] = False  # agent 2 at steps 0 to 2
    adv = credit_by_hand(alive, torch.zeros(CREDIT_T, 1, 3, dtype=torch.bool))
    # the recipients' actions are masked and agent 0 is absent at arrival: nothing is given
    m0 = [0.25 * ((q[2] - v(2, 1, [])) + (q[2] - v(2, 2, []))), 0.25 * (q[3] - v(3, 1, [])), 0.0, 0.0, 0.0]
    torch.testing.assert_close(adv.message[:, 0, 0], torch.tensor(m0))
    assert (adv.action[2:, 0, 0] == 0).all()  # absent: no action credit either
    assert adv.action[2, 0, 1].item() == pytest.approx(q[2] - v(2, 1, [2]))  # the absent agent 0 is not given


def test_standard_credit_by_hand() -> None:
    """Standard estimator (paper eq. 7): action and message of agent j at t share Q_t - V1(s_t, a_t^{-j}, m^{-j}),
    V1 judging j with every other present agent's action given and j's own inbox; drops change nothing."""
    q, v = CREDIT_Q, stub_value
    alive = torch.ones(CREDIT_T, 1, 3, dtype=torch.bool)
    alive[3:, 0, 2] = False
    dropped = torch.zeros(CREDIT_T, 1, 3, dtype=torch.bool)
    dropped[0, 0, 0] = True
    received = torch.zeros(CREDIT_T, 1, 3, dtype=torch.bool)
    received[2:, 0, 1] = True  # agent 1 hears a 1 from step 2 on; agents 0 and 2 hear zeros
    adv = credit_by_hand(alive, dropped, "standard", received)
    others = [[1, 2], [0, 2], [0, 1]]
    want = torch.zeros(CREDIT_T, 3)
    for t in range(CREDIT_T):
        for j in range(3):
            if alive[t, 0, j]:
                given = [k for k in others[j] if alive[t, 0, k]]
                want[t, j] = q[t] - v(t, j, given) - 50 * float(received[t, 0, j])
    torch.testing.assert_close(adv.action[:, 0], want)
    torch.testing.assert_close(adv.message[:, 0], want)


def test_the_critic_step_regresses_on_the_returns_of_its_own_episodes() -> None:
    """A minibatch's critic step (columns in any order) fits each of its steps' values to that step's Q_t."""
    learner, ro = _batch(config(env_kwargs={"steps": 4}))
    adv = learner.advantages(ro)
    cols = torch.tensor([5, 2, 7])
    it, ib = ro.valid[:, cols].nonzero(as_tuple=True)
    with torch.no_grad():
        values = learner.critic_values(ro, it, cols[ib])
    want = (values - adv.returns[it, cols[ib], None]).pow(2).mean().item()
    assert not torch.equal(adv.returns[:, cols], adv.returns[:, : len(cols)])  # the check has power
    assert learner._critic_step(ro, adv, cols) == pytest.approx(want, rel=1e-5)


def test_returns_are_the_estimators() -> None:
    r = torch.tensor([[1.0], [1.0]])
    q = discounted_returns(r, torch.tensor([[False], [True]]), torch.ones(2, 1, dtype=torch.bool), 0.5)
    torch.testing.assert_close(q[:, 0], torch.tensor([1.5, 1.0]))


# ---------------------------------------------------------------------------------------------- purity
def _batch(cfg: EnvTrainConfig) -> tuple[EnvLearner, EnvRollout]:
    vec = VecEnv(env_factory(cfg), 8)
    torch.manual_seed(0)
    learner = EnvLearner(cfg, vec.layout)
    return learner, play(vec, learner.policy, np.random.SeedSequence(0), torch.Generator().manual_seed(0))


def _grads(learner: EnvLearner, ro: EnvRollout, adv: Advantages) -> dict[str, torch.Tensor]:
    learner.policy.zero_grad()
    loss, _ = learner.policy_loss(ro, adv, torch.arange(ro.valid.shape[1]))
    loss.backward()
    return {
        k: p.grad.clone() if p.grad is not None else torch.zeros_like(p) for k, p in learner.policy.named_parameters()
    }


@pytest.mark.parametrize(
    ("clip", "box", "messages"), [(0.0, False, "bitwise"), (0.2, False, "bitwise"), (0.2, True, "bitwise"),
                                  (0.2, False, "onehot")]
)  # fmt: skip
def test_pure_zero_advantages_and_entropy_give_zero_gradient(clip: float, box: bool, messages: str) -> None:
    """SPEC 7: every gradient that reaches the action and message heads is policy gradient + entropy."""
    cfg = config(entropy_action=0.0, entropy_message=0.0, clip=clip, env_kwargs={"box": box}, messages=messages)
    learner, ro = _batch(cfg)
    zero = Advantages(torch.zeros_like(ro.logp_action), torch.zeros_like(ro.logp_action), torch.zeros_like(ro.rewards))
    assert all((g == 0).all() for g in _grads(learner, ro, zero).values())
    grads = _grads(learner, ro, learner.advantages(ro))  # the check can fail: real advantages move both heads
    assert grads["message_out.weight"].abs().sum() > 0 and grads["action_out.weight"].abs().sum() > 0


def test_fixed_agent_gets_no_action_gradient() -> None:
    """An agent in `fixed_actions`: its recorded actions change neither the loss nor the gradient."""
    cfg = config(channel={"bits": 2, "fixed_actions": {"listener": 0}})
    learner, ro = _batch(cfg)
    adv = learner.advantages(ro)
    assert (adv.action[:, :, 1] == 0).all() and adv.action[:, :, 0].abs().sum() >= 0
    other = ro._replace(actions=ro.actions.clone(), logp_action=ro.logp_action.clone())
    other.actions[:, :, 1] = 1 - other.actions[:, :, 1]
    other.logp_action[:, :, 1] -= 3.0
    a, b = _grads(learner, ro, adv), _grads(learner, other, adv)
    assert all(torch.equal(a[k], b[k]) for k in a)
    # the same change to the listener when it is not fixed does move the gradient
    free, ro2 = _batch(config())
    adv2 = free.advantages(ro2)
    other2 = ro2._replace(actions=ro2.actions.clone())
    other2.actions[:, :, 1] = 1 - other2.actions[:, :, 1]
    a2, b2 = _grads(free, ro2, adv2), _grads(free, other2, adv2)
    assert not torch.equal(a2["action_out.weight"], b2["action_out.weight"])


def test_every_agent_fixed_normalises_no_action_advantage_and_warns_nothing() -> None:
    """With every agent's action fixed only the messages learn: no action advantage is left to divide by its
    standard deviation, which torch computed over no entry with a warning to the user ("degrees of freedom is
    <= 0"); the action advantages stay zero and the messages' are normalised as before."""
    cfg = config(channel={"bits": 2, "fixed_actions": {"speaker": 0, "listener": 0}}, adv_norm=True)
    learner, ro = _batch(cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        adv = learner.advantages(ro)
    assert (adv.action == 0).all() and adv.message.abs().sum() > 0


# ---------------------------------------------------------------------------------------------- runs
def test_resume_gives_the_uninterrupted_run(tmp_path: Path) -> None:
    cfg = config(episodes=32)
    whole = train_env(cfg, tmp_path / "whole", progress=False)
    train_env(dataclasses.replace(cfg, episodes=16), tmp_path / "split", progress=False)
    split = train_env(cfg, tmp_path / "split", resume=True, progress=False)
    from safetensors.torch import load_file

    wa, wb = load_file(str(whole)), load_file(str(split))
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    rows = [(tmp_path / r / "metrics.csv").read_text().splitlines() for r in ("whole", "split")]
    strip = [[",".join(x for i, x in enumerate(line.split(",")) if i != 3) for line in r] for r in rows]  # wall_s
    assert strip[0] == strip[1] and len(strip[0]) == 5


@pytest.mark.parametrize(("reward", "shown"), [("nan", "nan"), ("inf", "inf"), (None, "None"), ("high", "'high'")])
def test_a_reward_that_is_not_a_finite_number_is_one_line(
    reward: Any, shown: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not "training diverged ... a smaller --lr may help": the env's value, named, before it reaches the learner."""
    kwargs = json.dumps({"reward": reward})
    argv = ["train", "--env", f"{__name__}:OddRewardEnv", "--env-kwargs", kwargs, "--num-envs", "8", "--episodes", "8"]
    code = main([*argv, "--hidden", "16", "--out", str(tmp_path / "run"), "--quiet", "--eval-episodes", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [
        f"bitcomm train: error: invalid rewards['speaker']={shown}: the env's rewards must be finite numbers"
    ], err
    assert not list(tmp_path.glob("run/checkpoints/*.safetensors"))  # nothing learned: the same command starts afresh


@pytest.mark.parametrize(
    ("reward", "line"),
    [
        ("missing", "invalid rewards=['listener']: the env gave none for 'speaker', which acted this step; a "
                    "ParallelEnv rewards every agent that acts (0.0 for no reward)"),
        ("array", "invalid rewards['speaker'] shape=(1,): the env's rewards must be scalars, one number per agent "
                  "(not arrays)"),
    ],
)  # fmt: skip
def test_a_reward_missing_or_not_a_scalar_is_one_line(
    reward: str, line: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A live agent left out of the rewards dict is the env's bug (PettingZoo's API test warns of it), not a reward
    of 0 to learn from; `np.array([1.0])` is named by its shape, not as "not a finite number"."""
    kwargs = json.dumps({"reward": reward})
    argv = ["train", "--env", f"{__name__}:OddRewardEnv", "--env-kwargs", kwargs, "--num-envs", "4", "--episodes", "4"]
    code = main([*argv, "--hidden", "16", "--out", str(tmp_path / "run"), "--quiet", "--eval-episodes", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [f"bitcomm train: error: {line}"], err


@pytest.mark.parametrize(
    ("odd", "line"),
    [
        ("nan", "invalid observations['listener']['observation']=nan: the env's observations must be finite numbers "
                "(as float32; the network cannot read NaN or infinity)"),
        ("inf", "invalid observations['listener']['observation']=inf: the env's observations must be finite numbers "
                "(as float32; the network cannot read NaN or infinity)"),
        ("state nan", "invalid state()=nan: the env's state must be finite numbers (as float32)"),
        ("state longer", "invalid state() size=3: must keep the size it had at reset (2 numbers once flattened, "
                         "what the critic reads)"),
        # a traceback from numpy's float32 conversion; None became NaN and was blamed as "not finite"
        ("state dict", "invalid state()='dict': must be an array of numbers (the critic reads it flattened)"),
        ("state none", "invalid state()='NoneType': must be an array of numbers (the critic reads it flattened)"),
        ("longer", "invalid observations['listener']['observation'] shape=(4,): must fit Box(0.0, 1.0, (3,), "
                   "float32) (3 numbers once flattened, not 4)"),
        ("scalar", "invalid observations['listener']['observation'] shape=(): must fit Box(0.0, 1.0, (3,), float32) "
                   "(3 numbers once flattened, not 1)"),
        ("missing", "invalid observations=['speaker']: the env gave none for 'listener', which is in env.agents; a "
                    "ParallelEnv observes every agent it lists"),
    ],
)  # fmt: skip
def test_an_observation_the_network_cannot_read_is_one_line(
    odd: str, line: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not a traceback from torch's sampler (NaN, inf), from numpy's broadcast (a longer observation), or nothing
    at all (a scalar spread over the space; a listed agent with no observation acted on zeros and was counted
    absent, so it was never learned from nor rewarded): the env's value, named."""
    kwargs = json.dumps({"odd": odd})
    argv = ["train", "--env", f"{__name__}:OddObservationEnv", "--env-kwargs", kwargs, "--num-envs", "4"]
    code = main([*argv, "--episodes", "4", "--hidden", "16", "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [f"bitcomm train: error: {line}"], err


@pytest.mark.parametrize(
    ("obs", "value", "outside"),
    [
        ("discrete from 1", 0, "0 is not a value of Discrete(3, start=1)"),  # one-hot at index -1: read as 3
        ("discrete from -1", np.int64(-2), "-2 is not a value of Discrete(3, start=-1)"),
        ("multidiscrete", np.array([-1, 0]), "-1 is not a value of MultiDiscrete([2 3])"),
        ("multibinary", np.array([0, 2], np.int8), "2 is not a value of MultiBinary(2)"),  # passed on as a 2
        ("dict", {"cell": -1, "near": np.zeros(2)}, "-1 is not a value of Discrete(2)"),
    ],
)
def test_a_discrete_observation_outside_its_space_is_one_line(obs: str, value: Any, outside: str) -> None:
    """gymnasium's flatten reads these as other values without a word; the values inside still pass."""
    layout = VecEnv(env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs={"obs": obs})), 1).layout
    with pytest.raises(ConfigError, match=re.escape(f"does not fit {layout.obs_spaces[0]} ({outside})")):
        flat_row(layout, 0, value)
    assert flat_row(layout, 0, layout.obs_spaces[0].sample()).size == layout.obs_sizes[0]


@pytest.mark.parametrize(
    ("obs", "value", "shape"),
    [
        ("image", np.zeros((3, 2, 2), np.uint8), "(3, 2, 2) is not the space's (2, 2, 3)"),  # a transposed image
        ("box 2x2", np.zeros(4), "(4,) is not the space's (2, 2)"),
        ("dict", {"cell": np.array([0, 1]), "near": np.zeros(2)}, "(2,) is not the space's ()"),  # Discrete's one-hot
        ("discrete from 1", np.array([2]), None),
        ("dict", {"cell": 0, "near": np.zeros((2, 1))}, None),  # an axis of length 1 moves no number
        ("multibinary", np.zeros((1, 2), np.int8), None),
    ],
)
def test_an_observation_of_the_right_size_in_another_shape_is_one_line(obs: str, value: Any, shape: str | None) -> None:
    """Its numbers were read in the space's order without a word: a (3, 2, 2) image for a (2, 2, 3) space reached
    the network with its pixels scrambled, a Discrete(2)'s value given as its one-hot [0, 1] set both entries of
    the one-hot gymnasium made. Axes of length 1 change no number's place and pass."""
    layout = VecEnv(env_factory(config(env=f"{__name__}:SpacesEnv", env_kwargs={"obs": obs})), 1).layout
    if shape is None:
        assert flat_row(layout, 0, value).size == layout.obs_sizes[0]
        return
    with pytest.raises(ConfigError, match=re.escape(f"does not fit {layout.obs_spaces[0]} (shape {shape}: which")):
        flat_row(layout, 0, value)


def test_an_env_error_mid_run_saves_what_was_learned(tmp_path: Path) -> None:
    """The first copy gives NaN rewards from its third reset (spaces, batch 0, batch 1): batch 0 is learned and
    saved, as when a worker dies, so that the run loses nothing when its env is mended."""
    cfg = config(env=f"{__name__}:OddRewardEnv", env_kwargs={"reward": "nan", "from_reset": 3})
    with pytest.raises(ConfigError) as err:
        train_env(cfg, tmp_path / "run", progress=False)
    saved = tmp_path / "run" / "checkpoints" / "ckpt_000000008.safetensors"
    assert str(err.value) == (
        f"invalid rewards['speaker']=nan: the env's rewards must be finite numbers; saved after 8 episodes as "
        f"{saved}; {RESUMES}"
    )
    assert saved.is_file()


def test_an_env_that_raises_mid_run_keeps_its_traceback_and_saves_what_was_learned(tmp_path: Path) -> None:
    """The env's own exception is its author's bug report, so it is not turned into one line; the run saves first."""
    cfg = config(env=f"{__name__}:OddRewardEnv", env_kwargs={"reward": "raise", "from_reset": 3})
    with pytest.raises(ZeroDivisionError, match="the env's own bug") as err:
        train_env(cfg, tmp_path / "run", progress=False)
    saved = tmp_path / "run" / "checkpoints" / "ckpt_000000008.safetensors"
    assert err.value.__notes__ == [
        f"bitcomm: the env raised this while playing a batch; saved after 8 episodes as {saved}; {RESUMES}"
    ]
    assert saved.is_file()


def test_ctrl_c_again_while_a_batch_plays_on_saves_the_batches_before_and_resume_plays_it_afresh(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A wrapped env's episodes end only when the env ends them: where they go on, the first Ctrl-C (a stop after
    the batch) never comes due, and the second ended the run unsaved, losing up to `checkpoint_seconds` of
    training. It now keeps every batch learned, drops the one being played, and a resume plays that batch as the
    run would have (the same episodes and draws: its metrics match an uninterrupted run's)."""
    from bitcomm.stop_signals import Stopped

    cfg = config(env=f"{__name__}:OddRewardEnv", env_kwargs={"reward": "interrupt", "from_reset": 3},
                 checkpoint_seconds=3600, episodes=16)  # fmt: skip
    with pytest.raises(Stopped) as err:
        train_env(cfg, tmp_path / "run", progress=False)
    saved = tmp_path / "run" / "checkpoints" / "ckpt_000000008.safetensors"
    assert err.value.exit_code == 128 + signal.SIGINT and saved.is_file()
    assert (err.value.checkpoint, err.value.episodes) == (saved, 8)  # for a notebook, which reads no printed line
    assert capsys.readouterr().err.strip() == f"stopped after 8 episodes on SIGINT, saved as {saved}; {RESUMES}"
    resumed = train_env(cfg, tmp_path / "run", resume=True, progress=False)  # fresh copies: 2 resets, no ^C
    calm = dataclasses.replace(cfg, env_kwargs={"reward": "interrupt", "from_reset": 10**9})
    whole = train_env(calm, tmp_path / "whole", progress=False)
    from safetensors.torch import load_file

    wa, wb = load_file(str(whole)), load_file(str(resumed))
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    rows = [(tmp_path / r / "metrics.csv").read_text().splitlines() for r in ("whole", "run")]
    strip = [[",".join(x for i, x in enumerate(line.split(",")) if i != 3) for line in r] for r in rows]  # wall_s
    assert strip[0] == strip[1] and len(strip[0]) == 3


@pytest.mark.usefixtures("trust_test_envs")
def test_evaluating_a_run_closes_the_envs_it_made(tmp_path: Path) -> None:
    path = train_env(config(env=f"{__name__}:CountedEnv"), tmp_path / "run", progress=False)
    CountedEnv.made.clear()
    evaluate_env(path, 4, seed=0)
    assert CountedEnv.made and all(env.closed for env in CountedEnv.made)


def failing_factory() -> None:
    """A factory whose error spans two lines (as a validation error listing its fields does)."""
    raise RuntimeError("bad map\nsee the log")


@pytest.mark.parametrize(
    ("flags", "names"),
    [
        (["--env", "no_such_module_xyz:make"], "cannot be imported"),
        (["--env", f"{__name__}:failing_factory"], "failed with them (RuntimeError: bad map see the log)"),
        (["--env", f"{__name__}:NoSuchFactory"], "no callable 'NoSuchFactory'"),
        (["--env", "json:JSONDecoder"], "not a PettingZoo ParallelEnv"),
        (["--env", SPEC, "--env-kwargs", "{bad"], "--env-kwargs"),
        (["--env", SPEC, "--env-kwargs", '{"nope": 1}'], "env_kwargs"),
        (["--env", SPEC, "--topology", "star"], "--topology"),
        (["--env", SPEC, "--fixed-actions", "[1]"], "--fixed-actions"),
        (["--topology", "ring"], "only with --env"),
        (["--env", SPEC, "--goal-coef", "1"], "not used with --env"),
        (["--env", SPEC, "--size", "5"], "a grid option, not used with --env"),
        (["--env", SPEC, "--agents", "3"], "a grid option, not used with --env"),
        (["--env", SPEC, "--recipe", "supervised"], "not used with --env"),
        (["--env", SPEC, "--lr", "1e300"], "the largest float32"),  # was a traceback from inside Adam
        (["--env", SPEC, "--hidden", "0"], "invalid hidden=0: must be an integer >= 1"),  # was named as (0, 0)
    ],
)
def test_cli_errors_are_one_line(
    flags: list[str], names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["train", *flags, "--out", str(tmp_path / "run"), "--quiet", "--eval-episodes", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and names in err[0], err


BAD_ENVS = [
    (["--env", "no_such_module_xyz:make"], "cannot be imported"),
    (["--env", f"{__name__}:SpacesEnv", "--env-kwargs", '{"act": "dict"}'], "action_space('a')"),
    (["--env", SPEC, "--messages", "onehot", "--bits", "30"], "invalid bits=30: one-hot messages over 2^30 words"),
    # every episode ended at its first step with no one acting: a run that learned nothing and reported return 0
    (["--env", f"{__name__}:NobodyEnv"], "invalid env.agents=[]: after reset(seed=0): no agent would act"),
    # possible_agents set only in reset: an AttributeError from the maker, before the wrapper could say it
    (["--env", f"{__name__}:NamedInResetEnv"], "invalid possible_agents=None: NamedInResetEnv has none before reset"),
]


@pytest.mark.parametrize(("flags", "names"), BAD_ENVS)
def test_cli_refuses_a_bad_env_before_it_prints_or_writes(
    flags: list[str], names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["train", *flags, "--hidden", "16", "--out", str(tmp_path / "run"), "--quiet"])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and names in err, (out, err)
    assert not (tmp_path / "run").exists()


class WideEnv(SignalEnv):
    """SignalEnv whose listener observes `width` numbers (zeros but the last) and whose episodes last `steps`."""

    def __init__(self, width: int = 3, steps: int = 2) -> None:
        super().__init__(steps=steps)
        self._obs = {**self._obs, "listener": spaces.Box(0, 1, (width,), np.float32)}

    def _observe(self) -> dict[str, np.ndarray]:
        obs = super()._observe()
        wide = np.zeros(self._obs["listener"].shape, np.float32)
        wide[-1] = obs["listener"][-1]
        return {**obs, "listener": wide}


def test_a_batch_whose_episodes_outgrow_memory_is_one_line_before_it_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """PettingZoo's cooperative_pong observes 403,200 floats per agent and a state of as many: 32 episodes side by
    side hold 0.43 GB a step (with the copies learning makes), so a batch of its 900-step episodes wants some
    400 GB and ended in a MemoryError traceback or the OOM killer. An episode's length is not known in advance:
    the step that would not fit is refused, naming what to change, and nothing is saved (nothing was learned)."""
    from bitcomm.learn import env_rollout

    cfg = config(env=f"{__name__}:WideEnv", env_kwargs={"width": 1000, "steps": 50})
    per_step = env_rollout.held_step_bytes(VecEnv(env_factory(cfg), 1).layout, cfg.num_envs, learning=True)
    monkeypatch.setattr(env_rollout, "available_bytes", lambda: 10 * per_step + 1)
    argv = ["train", "--env", cfg.env, "--env-kwargs", json.dumps(cfg.env_kwargs), "--bits", "2", "--num-envs", "8"]
    code = main(
        [*argv, "--episodes", "8", "--hidden", "16", "--out", str(tmp_path / "run"), "--quiet", "--eval-episodes", "0"]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [
        f"bitcomm train: error: invalid num-envs=8: 8 episodes side by side outgrow memory at step 11 (2 agents "
        f"observing 1,000 numbers, a state of 2,000: about {per_step / (1 << 30):.2f} GB a step, kept to the "
        f"episodes' end; 0.0 GB available); give fewer --num-envs, or shorter episodes (the env's own option in "
        "--env-kwargs, e.g. max_cycles)"
    ], err
    assert not list(tmp_path.glob("run/checkpoints/*.safetensors"))
    monkeypatch.setattr(env_rollout, "available_bytes", lambda: 50 * per_step)  # 50 steps: it fits
    assert len(play(VecEnv(env_factory(cfg), 8), EnvLearner(cfg, EnvLayout.of(env_factory(cfg)())).policy,
                    np.random.SeedSequence(0), None).length) == 8  # fmt: skip


def test_a_one_hot_batch_counts_the_tables_it_acts_on_as_it_plays(monkeypatch: pytest.MonkeyPatch) -> None:
    """A one-hot policy acts on float32 tables of 2^K per agent and episode at every step (logits, softmax,
    cumulative sum, heard slots): the commands count them before they play, and `play`'s own guard did not, so a
    batch that fit its steps and not its tables ran out of memory mid-episode. Refused at the step that would not
    fit with them, naming them."""
    from bitcomm.learn import env_rollout
    from bitcomm.memory import acting_bytes

    cfg = config(env=f"{__name__}:WideEnv", env_kwargs={"width": 1000, "steps": 50}, messages="onehot",
                 channel={"bits": 12})  # fmt: skip
    layout = EnvLayout.of(env_factory(cfg)())
    per_step, tables = env_rollout.held_step_bytes(layout, 8), 8 * acting_bytes(2, 12, 1)
    assert tables > per_step  # without them, the batch would pass step 11
    policy = EnvLearner(cfg, layout).policy
    monkeypatch.setattr(env_rollout, "available_bytes", lambda: 10 * per_step + tables + 1)
    with pytest.raises(ConfigError, match=r"outgrow memory at step 11 .* besides 0\.00 GB of one-hot tables it"):
        play(VecEnv(env_factory(cfg), 8), policy, np.random.SeedSequence(0), None)
    monkeypatch.setattr(env_rollout, "available_bytes", lambda: 50 * per_step + tables)  # 50 steps: it fits
    assert len(play(VecEnv(env_factory(cfg), 8), policy, np.random.SeedSequence(0), None).length) == 8


def test_the_memory_check_counts_what_an_env_run_holds(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before a line is printed: the networks' first layers read the observation and the state (a wide env's take
    GBs), a batch's first step, and with one-hot messages the float32 tables of 2^K per agent and episode a batch
    acts on (logits, softmax, cumulative sum, heard slots: what the grid's check counts), which were left out."""
    from bitcomm.commands import env_train, flags

    cfg = config(messages="onehot", channel={"bits": 16}, num_envs=32, hidden=(128, 128))
    wide = (1 << 16) * (128 + 128) * 16  # the policy's message output and input (one slot), x16: Adam
    acting = 32 * 2 * (1 << 16) * (3 + 1) * 4  # 2 agents hearing 1 slot each, 32 episodes
    monkeypatch.setattr(flags, "available_bytes", lambda: wide + acting)
    with pytest.raises(ConfigError, match=r"invalid bits=16: one-hot messages over 2\^16 words \(1 run\(s\) at once"):
        env_train.check_env([cfg])
    monkeypatch.setattr(flags, "available_bytes", lambda: 2 * (wide + acting))
    env_train.check_env([cfg])  # it fits
    big = config(env=f"{__name__}:WideEnv", env_kwargs={"width": 10**6}, hidden=(64,))
    monkeypatch.setattr(flags, "available_bytes", lambda: 8 << 30)  # 3 M inputs x 64 x 16 bytes: 2.9 GB, fits
    env_train.check_env([big])
    monkeypatch.setattr(flags, "available_bytes", lambda: 2 << 30)
    with pytest.raises(ConfigError) as refused:
        env_train.check_env([big])
    said = str(refused.value)
    assert said.startswith(
        "invalid hidden=64: the networks (2 agents observing 1,000,000 numbers, a state of 2,000,000"
    )
    assert said.endswith(
        "; the first layers read every number observed and of the state: give a narrower --hidden or an "
        "env that observes fewer"
    )


def test_the_memory_check_counts_the_critics_queries_of_many_agents_with_many_actions(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The update asks the critic, at each step of the batch, n action baselines and (improved) n per recipient rank,
    each reading every agent's action one-hot: n^3 times the actions. 12 agents of 4096 actions, all hearing all,
    read 7 M numbers a step (28 MB; 6 agents took 2 GB for 16 episodes of 10 steps). Uncounted, the check let such
    a run through to the OOM killer, unsaved; now it is one line before anything is written. An evaluation asks the
    critic nothing: its batch is not refused for them."""
    from bitcomm.commands import env_train, flags
    from bitcomm.learn import env_rollout

    agents = [f"x{i}" for i in range(12)]
    cfg = config(env=f"{__name__}:SpacesEnv", env_kwargs={"act": "multibinary 12", "agents": agents}, hidden=(16,))
    monkeypatch.setattr(flags, "available_bytes", lambda: 400 << 20)  # 3 x 8 episodes x 28 MB do not fit
    with pytest.raises(ConfigError, match=r"^invalid num-envs=8: 8 episodes side by side, for one step \(12 agents"):
        env_train.check_env([cfg])
    monkeypatch.setattr(env_rollout, "available_bytes", lambda: 400 << 20)
    policy = EnvLearner(cfg, EnvLayout.of(env_factory(cfg)())).policy
    with pytest.raises(ConfigError, match=r"at step 1 .* a step \(0\.63 GB of it the critic's, reading every agent's"):
        play(VecEnv(env_factory(cfg), 8), policy, np.random.SeedSequence(0), None, learning=True)  # a batch, mid-run
    assert len(play(VecEnv(env_factory(cfg), 8), policy, np.random.SeedSequence(0), None, flag="episodes").length) == 8
    monkeypatch.setattr(flags, "available_bytes", lambda: 1 << 30)
    env_train.check_env([cfg])  # it fits


@pytest.mark.usefixtures("trust_test_envs")  # the run is read back
def test_a_one_hot_env_run_too_wide_to_evaluate_that_many_episodes_is_refused_before_it_plays(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`bitcomm eval RUN` of a one-hot run on a wrapped env plays 256 episodes side by side, each acting on float32
    tables of 2^K per agent (logits, softmax, cumulative sum, heard slots): the grid's eval counts them, this one
    did not, and at 16-24 bits ran out of memory mid-play. Refused in one line naming --episodes, as are
    `train --env --eval-episodes` and a study's evaluations before they train."""
    from bitcomm.commands import flags
    from bitcomm.learn.env_rollout import HELD_COPIES, step_bytes
    from bitcomm.memory import acting_bytes

    run = str(tmp_path / "run")
    argv = ["train", "--env", SPEC, "--messages", "onehot", "--bits", "10", "--num-envs", "8", "--hidden", "16"]
    assert main([*argv, "--episodes", "8", "--out", run, "--quiet", "--eval-episodes", "0", "--threads", "1"]) == 0
    layout = VecEnv(env_factory(config(channel={"bits": 10})), 1).layout
    need = 256 * (acting_bytes(2, 10, 1) + HELD_COPIES * step_bytes(layout))  # 8 MB of tables
    monkeypatch.setattr(flags, "available_bytes", lambda: need - 1)
    capsys.readouterr()
    study = ["compare", "--env", SPEC, "--bits", "10", "--techniques", "improved-onehot", "--seeds", "1"]
    refused = [
        (["eval", run, "--episodes", "1000"], "episodes"),
        ([*argv, "--eval-episodes", "1000", "--out", str(tmp_path / "t")], "eval-episodes"),
        ([*study, "--eval-episodes", "1000", "--out", str(tmp_path / "c")], "eval-episodes"),
    ]
    for command, flag in refused:
        assert main(command) == 2
        out, err = capsys.readouterr()
        assert out == "" and len(err.strip().splitlines()) == 1, (out, err)
        assert f"invalid {flag}=1000: 256 episodes side by side with one-hot messages over 2^10 words" in err
    assert not (tmp_path / "t").exists() and not (tmp_path / "c").exists()  # refused before training
    monkeypatch.setattr(flags, "available_bytes", lambda: need)
    assert main(["eval", run, "--episodes", "1000"]) == 0
    assert "1000 episodes, mean team return" in capsys.readouterr().out


@pytest.mark.usefixtures("trust_test_envs")  # the run is read back: eval, --resume
def test_cli_trains_and_evaluates_with_the_channel_cut(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / "run")
    argv = ["train", "--env", SPEC, "--bits", "2", "--num-envs", "8", "--episodes", "8", "--hidden", "16"]
    assert main([*argv, "--out", out, "--quiet", "--eval-episodes", "0", "--threads", "1"]) == 0
    assert f"; env {SPEC}; torch threads: 1" in capsys.readouterr().out  # as the grid's first line says them
    assert main(["eval", out, "--episodes", "20", "--drop-prob", "1", "--json"]) == 0
    assert '"mean_team_return"' in capsys.readouterr().out
    assert main(["eval", out, "--size", "5"]) == 2  # a grid flag on a wrapped-env run
    for changed in (["--bits", "3"], ["--hidden", "8"], ["--size", "5"], ["--lr", "0.5"]):  # what it is: one line
        assert main(["train", "--resume", "--out", out, *changed, "--episodes", "16", "--quiet"]) == 2
        assert f"invalid {changed[0][2:]}=" in capsys.readouterr().err
    same = ["--bits", "2", "--hidden", "16", "--keep-checkpoints", "1"]  # what it was, and how often it saves
    assert main(["train", "--resume", "--out", out, *same, "--episodes", "16", "--quiet", "--eval-episodes", "0"]) == 0
    assert json.loads((Path(out) / "config.json").read_text())["keep_checkpoints"] == 1
    checkpoint = str(Path(out) / "checkpoints" / "ckpt_000000016.safetensors")
    assert main(["eval", checkpoint, "--episodes", "10"]) == 0
    assert "10 episodes, mean team return" in capsys.readouterr().out


@pytest.mark.usefixtures("trust_test_envs")  # --resume reads the run back
def test_a_finished_env_run_whose_curve_cannot_be_drawn_warns_and_succeeds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """As on the grid: the run is saved, so a refused drawing of its curve is one warning and status 0."""
    from matplotlib.figure import Figure

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    out = tmp_path / "run"
    argv = ["train", "--env", SPEC, "--bits", "2", "--num-envs", "8", "--episodes", "8", "--hidden", "16"]
    with monkeypatch.context() as refused:  # not `undo()`: that would undo the fixture's trust too
        refused.setattr(Figure, "savefig", full)
        assert main([*argv, "--out", str(out), "--quiet", "--eval-episodes", "0", "--threads", "1"]) == 0
    err = capsys.readouterr().err.strip()
    assert err == (
        f"warning: {str(out / 'learning_curve.png')!r}: No space left on device; the run is finished and saved; "
        f"`bitcomm train --resume --out {out}` draws it"
    )
    assert (out / "checkpoints" / "ckpt_000000008.safetensors").is_file()
    assert main(["train", "--resume", "--out", str(out), "--quiet", "--eval-episodes", "0"]) == 0
    assert (out / "learning_curve.png").is_file()


def test_an_env_run_without_out_writes_the_folder_the_help_names(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`bitcomm train --help` named only the grid's default folder, runs/<recipe>-..., for --out; a wrapped env's
    run has no recipe and is written to runs/env-<module>-<estimator>-<messages>-s<seed>."""
    from bitcomm.cli import build_parser

    monkeypatch.chdir(tmp_path)
    argv = ["train", "--env", SPEC, "--bits", "2", "--num-envs", "8", "--episodes", "8", "--hidden", "16"]
    assert main([*argv, "--quiet", "--eval-episodes", "0", "--threads", "1"]) == 0
    module = __name__.rpartition(".")[2]
    assert (tmp_path / "runs" / f"env-{module}-improved-bitwise-s0" / "config.json").is_file()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    help_text = " ".join(sub.choices["train"].format_help().split())
    assert "with --env runs/env-<module>-<estimator>-<messages>-s<seed>" in help_text


def test_resuming_a_grid_run_with_env_says_what_the_run_is(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Not "its config does not fit this bitcomm (KeyError: 'channel')"."""
    grid = str(tmp_path / "grid")
    assert main(["train", "--size", "3", "--bits", "4", "--episodes", "16", "--num-envs", "16", "--out", grid,
                 "--quiet", "--eval-episodes", "0", "--threads", "1"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["train", "--env", SPEC, "--resume", "--out", grid, "--episodes", "32", "--quiet"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"bitcomm train: error: invalid out={grid!r}: a run of the grid task, not of a wrapped env; resume it without "
        "--env"
    ]


# ---------------------------------------------------------------------------------------------- learning
@pytest.mark.usefixtures("trust_test_envs")  # evaluate_env reads the run back
def test_improved_bitwise_learns_to_use_the_channel(tmp_path: Path) -> None:
    """The listener can earn 1 per episode only by reading the speaker's message; with every message dropped
    it is right half the time. Improved + bitwise beats the same learner with the channel cut."""
    torch.set_num_threads(1)
    result = {}
    for drop in (0.0, 1.0):
        cfg = config(num_envs=64, episodes=64 * 40, hidden=(32, 32), lr=3e-3, channel={"bits": 2, "drop_prob": drop})
        path = train_env(cfg, tmp_path / f"drop{drop}", progress=False)
        result[drop] = evaluate_env(path, 512, seed=7).mean_team_return
    assert result[0.0] > 0.9 and result[1.0] < 0.7, result


def test_running_norm_matches_the_pooled_statistics() -> None:
    from bitcomm.policies.mlp import RunningNorm

    norm = RunningNorm((2, 3), enabled=True)
    x = torch.randn(5, 4, 2, 3, generator=torch.Generator().manual_seed(0)) * 3 + 1
    mask = torch.rand(5, 4, 2, generator=torch.Generator().manual_seed(1)) < 0.7
    norm.update(x[:2], mask[:2])
    norm.update(x[2:], mask[2:])
    for i in range(2):  # each agent's statistics over the samples where it was present
        kept = x[..., i, :][mask[..., i]]
        torch.testing.assert_close(norm.mean[i], kept.mean(0))
        torch.testing.assert_close(norm.var[i], kept.var(0, unbiased=False))
    assert torch.equal(RunningNorm((3,), enabled=False)(x[0, 0, 0]), x[0, 0, 0])


def test_the_critic_answers_k_queries_per_state_as_it_answers_each_alone() -> None:
    """`MlpCritic` computes a state's share of the first layer once for its consecutive queries; values and
    gradients are those of one state row per query."""
    cfg = config(estimator="standard")
    learner = EnvLearner(cfg, VecEnv(env_factory(cfg), 2).layout)
    critic, L = learner.critic, learner.layout
    torch.manual_seed(0)
    S, k = 5, 3
    state = torch.randn(S, L.state_size)
    queries = (
        torch.randint(0, L.n, (S * k,)),
        torch.randint(0, 2, (S * k, L.n)),
        torch.rand(S * k, L.n) < 0.5,
        torch.randint(0, 2, (S * k, L.slots, L.bits), dtype=torch.uint8),
    )
    shared, one_each = critic(state, *queries), critic(state.repeat_interleave(k, 0), *queries)
    torch.testing.assert_close(shared, one_each)
    params = list(critic.parameters())
    for g, e in zip(
        torch.autograd.grad(shared.square().sum(), params),
        torch.autograd.grad(one_each.square().sum(), params),
        strict=True,
    ):
        torch.testing.assert_close(g, e)
