"""BitChannel, the bit channel on any PettingZoo ParallelEnv (SPEC section 8): it passes PettingZoo's
conformance test on several inner envs; bits sent at step t are in the observation returned by step
t + delay - 1, zeros before; the topology routes each sender to its slot; flips act per bit and drops
per message at their rates; noise is seeded; an agent that left sends zeros; fixed actions replace
the inner action; the inner state is kept; bad input gets one line."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test, parallel_seed_test

from bitcomm.channel.core import index_to_bits
from bitcomm.channel.topology import recipients_of
from bitcomm.envs import goal_exchange_v0
from bitcomm.envs.channel_wrapper import BitChannel
from bitcomm.errors import ConfigError


class Toy(ParallelEnv):
    """Three agents a, b, c with a Box observation (the step count and a seeded draw) and Discrete(3)
    actions; c leaves after `c_steps` steps, the others are truncated after `steps`. No state()."""

    metadata = {"name": "toy_v0"}

    def __init__(
        self,
        steps: int = 8,
        c_steps: int | None = None,
        action_space: spaces.Space | None = None,
        observation_space: spaces.Space | None = None,
        agents: list[str] | None = None,
    ) -> None:
        self.possible_agents = ["a", "b", "c"] if agents is None else agents
        self.agents: list[str] = []
        self.steps, self.c_steps = steps, c_steps
        self._obs = observation_space if observation_space is not None else spaces.Box(0.0, 1e6, (2,), np.float32)
        self._act = action_space if action_space is not None else spaces.Discrete(3)
        self.received: list[dict[str, Any]] = []  # the inner actions of every step
        self.rng = np.random.default_rng()
        self.t = 0

    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs

    def action_space(self, agent: str) -> spaces.Space:
        return self._act

    def _observe(self) -> dict[str, Any]:
        if not isinstance(self._obs, spaces.Box) or self._obs.shape != (2,):  # a seeded draw from the space
            self._obs.seed(int(self.rng.integers(2**31)))
            return {a: self._obs.sample() for a in self.agents}
        return {a: np.array([self.t, self.rng.random()], dtype=np.float32) for a in self.agents}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.agents, self.t = self.possible_agents[:], 0
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        self.received.append(dict(actions))
        self.t += 1
        live = self.agents
        terminated = {a: a == "c" and self.t == self.c_steps for a in live}
        truncated = {a: self.t >= self.steps for a in live}
        obs = self._observe()
        self.agents = [a for a in live if not (terminated[a] or truncated[a])]
        return obs, dict.fromkeys(live, 0.0), terminated, truncated, {a: {"t": self.t} for a in live}

    def render(self) -> str:
        return "toy frame"


def mpe(name: str, **kwargs: Any) -> Callable[[], ParallelEnv]:
    def make() -> ParallelEnv:
        module = pytest.importorskip(f"mpe2.{name}")
        return module.parallel_env(**kwargs)

    return make


INNER = {
    "speaker_listener": mpe("simple_speaker_listener_v4"),
    "spread_3": mpe("simple_spread_v3", N=3),
    "reference": mpe("simple_reference_v3"),
    "spread_continuous": mpe("simple_spread_v3", N=3, continuous_actions=True),
    "toy_leaving": lambda: Toy(steps=10, c_steps=3),
    "toy_dict_obs_multidiscrete_action": lambda: Toy(
        steps=10,
        c_steps=3,
        observation_space=spaces.Dict(pos=spaces.Box(-1, 1, (2, 2), np.float32), cell=spaces.Discrete(4, start=1)),
        action_space=spaces.MultiDiscrete([2, 3]),
    ),
}


def zero_action(space: spaces.Space) -> Any:
    return np.zeros(space.shape, space.dtype) if not isinstance(space, spaces.Discrete) else 0


def run(env: BitChannel, messages: Callable[[int, str], np.ndarray], seed: int | None = 0) -> list[dict]:
    """Reset, then step to the end with the inner action 0 and `messages(t, agent)`; the observations of each step."""
    obs, _ = env.reset(seed=seed)
    out, t = [obs], 0
    while env.agents:
        actions = {a: {"action": zero_action(env.inner.action_space(a)), "message": messages(t, a)} for a in env.agents}
        out.append(env.step(actions)[0])
        t += 1
    return out


@pytest.mark.parametrize("name", INNER)
def test_parallel_api(name: str) -> None:
    env = BitChannel(INNER[name](), bits=4, delay=2, flip_prob=0.1, drop_prob=0.1, topology="ring", seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo reports soft failures as warnings
        parallel_api_test(env, num_cycles=100)


def test_parallel_seed_test_with_noise() -> None:
    make = INNER["spread_3"]
    parallel_seed_test(lambda: BitChannel(make(), bits=5, flip_prob=0.2, drop_prob=0.2), num_cycles=50)


def test_seeded_reproducible_and_different_with_another_seed() -> None:
    def heard(seed: int | None, ctor_seed: int | None = None) -> np.ndarray:
        """Every message heard in one noisy episode."""
        env = BitChannel(Toy(steps=20), bits=8, flip_prob=0.3, drop_prob=0.2, seed=ctor_seed)
        return np.stack(
            [o["messages"] for obs in run(env, lambda t, a: np.zeros(8, np.int8), seed=seed) for o in obs.values()]
        )

    assert np.array_equal(heard(3), heard(3))
    assert not np.array_equal(heard(3), heard(4))
    assert np.array_equal(heard(None, ctor_seed=5), heard(None, ctor_seed=5))  # the constructor's seed
    assert not np.array_equal(heard(None), heard(None))  # no seed at all: fresh noise


def test_a_numpy_seed_seeds_as_the_int_it_is() -> None:
    """A seed from a numpy array (a sweep's) reached the inner env as it was: gymnasium's seeding, which MPE2 uses,
    refused it in a traceback ("Seed must be a python integer"). It seeds both as the int it is."""
    for ctor, reset in ((None, np.int64(2)), (np.int64(2), None)):
        a, b = BitChannel(INNER["speaker_listener"](), seed=ctor), BitChannel(INNER["speaker_listener"](), seed=2)  # type: ignore[arg-type]
        obs_a, _ = a.reset(seed=reset)  # type: ignore[arg-type]
        obs_b, _ = b.reset(seed=None if reset is None else 2)
        assert all(np.array_equal(obs_a[k]["observation"], obs_b[k]["observation"]) for k in obs_b)


def test_spaces_and_attributes() -> None:
    inner = INNER["speaker_listener"]()
    env = BitChannel(inner, bits=3, topology=[("speaker_0", "listener_0")], fixed_actions={"speaker_0": 0})
    assert env.observation_space("listener_0") == spaces.Dict(
        observation=inner.observation_space("listener_0"), messages=spaces.MultiBinary((1, 3))
    )
    assert env.action_space("speaker_0") == spaces.Dict(action=spaces.Discrete(3), message=spaces.MultiBinary(3))
    assert env.possible_agents == ["speaker_0", "listener_0"] and env.inner is inner
    assert (env.bits, env.delay, env.channel_config.bits) == (3, 1, 3)
    assert env.recipients.tolist() == [[False, True], [False, False]]
    assert env.slot_senders.tolist() == [[-1], [0]]
    assert env.fixed_actions == {"speaker_0": 0}
    assert env.metadata["name"] == "simple_speaker_listener_v4_bitchannel"
    obs, _ = env.reset(seed=0)
    for agent, o in obs.items():
        assert env.observation_space(agent).contains(o)
    # the inner state is kept
    assert env.state_space is inner.state_space
    assert np.array_equal(env.state(), inner.state())
    env.close()


@pytest.mark.parametrize(
    "observation_space",
    [
        spaces.Box(0, 255, (4, 4, 3), np.uint8),  # an image
        spaces.Box(-1, 1, (), np.float32),  # a scalar
        spaces.Discrete(5, start=2),
        spaces.MultiDiscrete([3, 4]),
        spaces.MultiBinary(4),
        spaces.Tuple((spaces.Discrete(2), spaces.Box(-1, 1, (3,), np.float32))),
        spaces.Dict(cell=spaces.Discrete(3), seen=spaces.MultiBinary(2)),
    ],
    ids=repr,
)
def test_any_inner_observation_space_is_carried_as_it_is(observation_space: spaces.Space) -> None:
    env = BitChannel(Toy(steps=4, c_steps=2, observation_space=observation_space), bits=2, seed=0)
    assert env.observation_space("a")["observation"] is observation_space
    for obs in run(env, lambda t, a: np.ones(2, np.int8)):
        for agent, o in obs.items():
            assert env.observation_space(agent).contains(o), (agent, o)


def test_an_inner_reset_without_options_is_called_without_them() -> None:
    class NoOptions(Toy):
        def reset(self, seed: int | None = None) -> tuple[dict, dict]:  # type: ignore[override]
            return super().reset(seed)

    env = BitChannel(NoOptions(steps=2), bits=2)
    assert len(run(env, lambda t, a: np.zeros(2, np.int8))) == 3
    with pytest.raises(TypeError, match="options"):  # options given are passed on
        env.reset(seed=0, options={"x": 1})


def test_no_inner_state_no_state() -> None:
    env = BitChannel(Toy())
    env.reset(seed=0)
    assert not hasattr(env, "state_space")
    with pytest.raises(NotImplementedError):
        env.state()
    assert env.render() == "toy frame"


def pattern(t: int, agent: str) -> np.ndarray:
    """A distinct 6-bit message for each step and agent (never all zeros)."""
    return index_to_bits(np.int64(1 + 3 * t + "abc".index(agent)), 6).astype(np.int8)


@pytest.mark.parametrize("delay", [1, 2, 3])
def test_bits_sent_at_t_are_observed_at_t_plus_delay_minus_one(delay: int) -> None:
    env = BitChannel(Toy(steps=8), bits=6, delay=delay, topology="all")
    steps = run(env, pattern)
    assert all(not o["messages"].any() for o in steps[0].values())  # reset() returns zeros
    for t, obs in enumerate(steps[1:]):  # obs returned by step t
        sent_at = t - delay + 1
        for agent, o in obs.items():
            senders = [s for s in "abc" if s != agent]
            want = [pattern(sent_at, s) if sent_at >= 0 else np.zeros(6, np.int8) for s in senders]
            assert np.array_equal(o["messages"], np.stack(want)), (t, agent)
    # a reset forgets what is in flight
    obs, _ = env.reset()
    assert all(not o["messages"].any() for o in obs.values())


def test_topology_matrices() -> None:
    agents = ["a", "b", "c"]
    assert recipients_of(agents, "all").tolist() == [[0, 1, 1], [1, 0, 1], [1, 1, 0]]
    assert recipients_of(agents, "ring").tolist() == [[0, 1, 0], [0, 0, 1], [1, 0, 0]]  # i tells i + 1
    assert recipients_of(agents, [("c", "a"), ("b", "a")]).tolist() == [[0, 0, 0], [1, 0, 0], [1, 0, 0]]
    assert recipients_of(agents, lambda s, r: s < r).tolist() == [[0, 1, 1], [0, 0, 1], [0, 0, 0]]
    matrix = np.array([[0, 1, 0], [0, 0, 0], [1, 1, 0]], dtype=bool)  # the matrix itself, as numpy builds it
    assert recipients_of(agents, matrix).tolist() == matrix.tolist()


def test_a_wrappers_recipients_given_back_as_its_topology_build_the_same_channel() -> None:
    ring = BitChannel(Toy(), topology="ring")
    again = BitChannel(Toy(), topology=ring.recipients)
    assert np.array_equal(again.recipients, ring.recipients)
    assert again.recipients is not ring.recipients  # a copy: editing one channel's matrix leaves the other's


@pytest.mark.parametrize(
    ("topology", "heard"),
    [
        ("all", {"a": "bc", "b": "ac", "c": "ab"}),
        ("ring", {"a": "c", "b": "a", "c": "b"}),
        ([("c", "a"), ("b", "a")], {"a": "bc", "b": "", "c": ""}),
        (lambda s, r: s < r, {"a": "", "b": "a", "c": "ab"}),
        (np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0]], dtype=bool), {"a": "bc", "b": "", "c": ""}),
    ],
)
def test_topology_routes_each_sender_to_its_slot(topology: Any, heard: dict[str, str]) -> None:
    env = BitChannel(Toy(steps=2), bits=6, topology=topology)
    obs = run(env, pattern)[1]  # delay 1: what was sent at step 0
    slots = max(len(s) for s in heard.values())
    for agent, senders in heard.items():
        want = np.zeros((slots, 6), np.int8)
        for s, sender in enumerate(senders):  # senders in possible_agents order
            want[s] = pattern(0, sender)
        assert np.array_equal(obs[agent]["messages"], want), agent


def test_flips_per_bit_at_their_rate() -> None:
    p, steps, bits = 0.1, 200, 30
    env = BitChannel(Toy(steps=steps), bits=bits, flip_prob=p, seed=0)
    received = np.stack(
        [o["messages"] for obs in run(env, lambda t, a: np.zeros(bits, np.int8))[1:] for o in obs.values()]
    )
    n = received.size  # 200 steps x 3 agents x 2 slots x 30 bits
    assert abs(received.mean() - p) < 4 * np.sqrt(p * (1 - p) / n)
    # flips are independent per bit: whole messages are not flipped together
    assert 0 < received.sum(-1).mean() < bits


def test_drops_whole_messages_at_their_rate_for_every_recipient() -> None:
    p, steps, bits = 0.3, 200, 5
    env = BitChannel(Toy(steps=steps), bits=bits, drop_prob=p, seed=0)
    env.reset(seed=0)
    read_zero = []
    for _ in range(steps):
        obs, _, _, _, infos = env.step({a: {"action": 0, "message": np.ones(bits, np.int8)} for a in env.agents})
        rows = np.stack([obs[a]["messages"] for a in "abc"])  # (3, 2, K), each a message from another agent
        assert np.isin(rows.sum(-1), (0, bits)).all()  # a message arrives whole or not at all
        # agent a is heard in slot 0 by b and c; b in slot 1 by a and slot 0 by c; c in slot 1 by a and b
        heard = {"a": [rows[1, 0], rows[2, 0]], "b": [rows[0, 0], rows[2, 1]], "c": [rows[0, 1], rows[1, 1]]}
        for sender, copies in heard.items():
            zero = [not c.any() for c in copies]
            assert zero[0] == zero[1] == infos[sender]["message_dropped"]  # every recipient reads zeros
            read_zero.append(zero[0])
    rate, n = np.mean(read_zero), len(read_zero)
    assert abs(rate - p) < 4 * np.sqrt(p * (1 - p) / n)


def test_an_agent_that_left_sends_zeros() -> None:
    # c leaves after 2 steps; with delay 2 its last message (step 1) is read with step 2's observation
    env = BitChannel(Toy(steps=8, c_steps=2), bits=6, delay=2)
    steps = run(env, lambda t, a: np.ones(6, np.int8))
    from_c = [obs["a"]["messages"][1] for obs in steps[1:]]  # a hears b then c
    assert [int(m.sum()) for m in from_c] == [0, 6, 6, 0, 0, 0, 0, 0]
    # with noise too: nothing from c once its messages in flight have arrived, noise on b's slot
    env = BitChannel(Toy(steps=30, c_steps=2), bits=6, delay=2, flip_prob=0.5, seed=0)
    steps = run(env, lambda t, a: np.zeros(6, np.int8))
    assert not any(obs["a"]["messages"][1].any() for obs in steps[4:])
    assert any(obs["a"]["messages"][0].any() for obs in steps[4:])


def test_a_step_takes_actions_of_live_agents_only() -> None:
    env = BitChannel(Toy(steps=8, c_steps=1), bits=2)
    env.reset(seed=0)
    act = {"action": 0, "message": np.ones(2, np.int8)}
    infos = env.step(dict.fromkeys("abc", act))[4]
    assert env.agents == ["a", "b"] and set(infos) == {"a", "b", "c"}
    infos = env.step(dict.fromkeys("abc", act))[4]  # c's action is ignored: it has left
    assert set(infos) == {"a", "b"} and env.inner.received[-1].keys() == {"a", "b"}
    with pytest.raises(KeyError, match="'b'"):
        env.step({"a": act})
    with pytest.raises(ValueError, match="b: message must be 2 bits"):
        env.step({"a": act, "b": {"action": 0, "message": np.array([0, 2])}})
    for plain in (0, {"action": 0}, (0, np.ones(2))):  # the inner action alone, or no message: one line naming both
        with pytest.raises(ValueError, match=r"b: action must be \{'action': <inner action>, 'message': 2 bits\}"):
            env.step({"a": act, "b": plain})


class KeepsFinished(Toy):
    """Toy with PettingZoo's rule broken: an agent that terminates or truncates stays in `agents`."""

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        live = list(self.agents)
        out = super().step(actions)
        self.agents = live
        return out


def test_an_env_that_keeps_a_finished_agent_while_others_play_on_is_one_line() -> None:
    """Kept, `c` would be asked for actions and its messages sent after it left; a learner would count it present."""
    act = {"action": 0, "message": np.ones(2, np.int8)}
    env = BitChannel(KeepsFinished(steps=8, c_steps=2), bits=2)
    env.reset(seed=0)
    env.step(dict.fromkeys("abc", act))
    with pytest.raises(ConfigError) as err:
        env.step(dict.fromkeys("abc", act))
    assert str(err.value) == (
        "invalid env.agents=['a', 'b', 'c']: 'c' terminated or truncated at this step but is still listed while "
        "others play on; a PettingZoo ParallelEnv removes an agent from env.agents once it is done"
    )
    # every agent still listed, all done, at the end of the episode: nothing is stepped after it, so it passes
    env = BitChannel(KeepsFinished(steps=2), bits=2)
    env.reset(seed=0)
    truncated = [env.step(dict.fromkeys("abc", act))[3] for _ in range(2)][-1]
    assert all(truncated.values()) and env.agents == ["a", "b", "c"]


class ListsAStranger(Toy):
    """Toy with PettingZoo's rule broken: agent "z", not in `possible_agents`, is listed from step `joins` on."""

    def __init__(self, joins: int) -> None:
        super().__init__(steps=4)
        self.joins = joins

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        out = super().reset(seed, options)
        self.agents += ["z"] if self.joins == 0 else []
        return out

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        out = super().step({a: act for a, act in actions.items() if a != "z"})
        self.agents += ["z"] if self.t >= self.joins else []
        return out


@pytest.mark.parametrize("joins", [0, 1])
def test_an_env_that_lists_an_agent_outside_possible_agents_is_one_line(joins: int) -> None:
    """The wrapper has no slot, topology row or spaces for it: it would be asked for an action no one can give
    (a `KeyError` from `step`), and its observation dropped."""
    env = BitChannel(ListsAStranger(joins), bits=2)
    with pytest.raises(ConfigError) as err:
        env.reset(seed=0)
        env.step(dict.fromkeys("abc", {"action": 0, "message": np.ones(2, np.int8)}))
    assert str(err.value) == (
        "invalid env.agents=['a', 'b', 'c', 'z']: 'z' is not in possible_agents ['a', 'b', 'c']; a PettingZoo "
        "ParallelEnv lists every agent that may play in possible_agents"
    )


class OlderApi(Toy):
    """Toy whose `reset` or `step` returns what PettingZoo's API does not: `odd` is "reset obs only" (gym's and an
    older PettingZoo's reset), "reset infos None", "step dones" (four values, one `dones` dict) or "step infos
    None"."""

    def __init__(self, odd: str) -> None:
        super().__init__(steps=4)
        self.odd = odd

    def reset(self, seed: int | None = None, options: dict | None = None) -> Any:
        obs, infos = super().reset(seed, options)
        return {"reset obs only": obs, "reset infos None": (obs, None)}.get(self.odd, (obs, infos))

    def step(self, actions: dict[str, Any]) -> Any:
        obs, rewards, terminated, truncated, infos = super().step(actions)
        if self.odd == "step dones":
            return obs, rewards, {a: terminated[a] or truncated[a] for a in terminated}, infos
        return obs, rewards, terminated, truncated, None if self.odd == "step infos None" else infos


RESET = "a PettingZoo ParallelEnv's reset returns (observations, infos), a dict keyed by agent each"
STEP = "a PettingZoo ParallelEnv's step returns (observations, rewards, terminations, truncations, infos), a dict"


@pytest.mark.parametrize(
    ("odd", "line"),
    [
        ("reset obs only", f"invalid env.reset()='dict': {RESET}"),  # "too many values to unpack"
        ("reset infos None", f"invalid env.reset()='tuple(dict, NoneType)': {RESET}"),
        ("step dones", f"invalid env.step()='tuple(dict, dict, dict, dict)': {STEP}"),  # "not enough values"
        ("step infos None", f"invalid env.step()='tuple(dict, dict, dict, dict, NoneType)': {STEP}"),
    ],
)
def test_an_env_that_returns_other_than_the_api_says_is_one_line(odd: str, line: str) -> None:
    """Not an unpacking error or an AttributeError from inside the wrapper: what came back, named, and what a
    ParallelEnv returns. (Two agents' observations alone were even unpacked as their names.)"""
    env = BitChannel(OlderApi(odd), bits=2)
    with pytest.raises(ConfigError) as err:
        env.reset(seed=0)
        env.step(dict.fromkeys("abc", {"action": 0, "message": np.ones(2, np.int8)}))
    assert str(err.value).startswith(line) and "\n" not in str(err.value), str(err.value)


class SeedlessReset(Toy):
    """Toy whose `reset` takes no seed (nor options)."""

    def reset(self) -> tuple[dict, dict]:  # type: ignore[override]
        return super().reset()


def test_an_env_whose_reset_takes_no_seed_is_one_line() -> None:
    """Every episode is seeded through `reset(seed=...)`: refused when wrapped, not a TypeError at the first reset."""
    with pytest.raises(ConfigError) as err:
        BitChannel(SeedlessReset())
    assert str(err.value) == (
        "invalid env.reset='reset()': must take seed=, as a PettingZoo ParallelEnv's reset(seed=None, options=None) "
        "does: every episode is seeded through it"
    )


def test_fixed_actions_replace_the_inner_action() -> None:
    toy = Toy(steps=3)
    env = BitChannel(toy, bits=2, fixed_actions={"b": 2})
    run(env, lambda t, a: np.zeros(2, np.int8))
    assert [r["b"] for r in toy.received] == [2, 2, 2] and [r["a"] for r in toy.received] == [0, 0, 0]


@pytest.mark.parametrize("space", [spaces.MultiDiscrete([2, 3]), spaces.MultiBinary(2)])
def test_a_fixed_action_written_as_a_list_reaches_the_env_as_an_array_of_its_space(space: spaces.Space) -> None:
    """`--fixed-actions` is JSON, so a MultiDiscrete or MultiBinary action comes as a list; the env gets the
    array of the space's dtype that every other action of the space is (an env may read `action.shape`)."""
    toy = Toy(steps=2, action_space=space)
    env = BitChannel(toy, bits=2, fixed_actions={"b": [1, 0]})
    run(env, lambda t, a: np.zeros(2, np.int8))
    fixed = [r["b"] for r in toy.received]
    assert all(isinstance(f, np.ndarray) and f.dtype == space.dtype and f.tolist() == [1, 0] for f in fixed), fixed


def test_fixed_actions_silence_the_speakers_own_comm_action() -> None:
    # the speaker's comm action is fixed at 0, so the listener always sees comm one-hot [1, 0, 0]
    env = BitChannel(INNER["speaker_listener"](), bits=3, fixed_actions={"speaker_0": 0})
    env.reset(seed=0)
    for _ in range(3):
        actions = {a: {"action": 2, "message": np.ones(3, np.int8)} for a in env.agents}
        obs = env.step(actions)[0]
        assert obs["listener_0"]["observation"][-3:].tolist() == [1.0, 0.0, 0.0]


class NamedInReset(Toy):
    """Toy that sets `possible_agents` only in `reset`, against PettingZoo's rule."""

    def __init__(self) -> None:
        super().__init__()
        del self.possible_agents

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self.possible_agents = ["a", "b", "c"]
        return super().reset(seed, options)


class NoSpaceForC(Toy):
    """Toy whose observation spaces are a dict that lacks agent c."""

    def observation_space(self, agent: str) -> spaces.Space:
        return {"a": self._obs, "b": self._obs}[agent]


BAD: dict[str, tuple[Callable[[], Any], str]] = {
    "bits 0": (lambda: BitChannel(Toy(), bits=0), "bits=0"),
    "bits 31": (lambda: BitChannel(Toy(), bits=31), "bits=31"),
    "delay 0": (lambda: BitChannel(Toy(), delay=0), "delay=0"),
    "flip -0.1": (lambda: BitChannel(Toy(), flip_prob=-0.1), "flip_prob=-0.1"),
    "drop 1.5": (lambda: BitChannel(Toy(), drop_prob=1.5), "drop_prob=1.5"),
    "not parallel": (lambda: BitChannel(goal_exchange_v0.env()), "env="),
    "no agents": (lambda: BitChannel(Toy(agents=[])), "possible_agents=[]"),
    "an agent twice": (lambda: BitChannel(Toy(agents=["a", "b", "a"])), "possible_agents=['a', 'b', 'a']"),
    # an env that names its agents only in reset stopped in an AttributeError
    "agents named only in reset": (lambda: BitChannel(NamedInReset()), "possible_agents=None: NamedInReset has none"),
    "agents not a list": (lambda: BitChannel(Toy(agents=3)), "possible_agents=3"),  # type: ignore[arg-type]
    # the env's own lookup raised from inside the wrapper
    "space lookup raises": (
        lambda: BitChannel(NoSpaceForC()),
        "invalid env='NoSpaceForC': its observation_space('c') raised KeyError: 'c'",
    ),
    "not a space": (lambda: BitChannel(Toy(action_space=[0, 1, 2])), "action_space('a')=[0, 1, 2]"),  # type: ignore[arg-type]
    "topology word": (lambda: BitChannel(Toy(), topology="star"), "topology='star'"),
    "unknown agent": (lambda: BitChannel(Toy(), topology=[("a", "z")]), "'z' is not an agent"),
    "self edge": (lambda: BitChannel(Toy(), topology=[("a", "a")]), "itself"),
    "duplicate edge": (lambda: BitChannel(Toy(), topology=[("a", "b"), ("a", "b")]), "twice"),
    "rule raises": (lambda: BitChannel(Toy(), topology=lambda s, r: 1 / 0), "ZeroDivisionError"),
    "rule not bool": (lambda: BitChannel(Toy(), topology=lambda s, r: 1), "must return a bool"),
    # a matrix was refused row by row as an edge list ("each edge must be a (sender, receiver) pair")
    "matrix shape": (lambda: BitChannel(Toy(), topology=np.zeros((2, 2), bool)), "must be (3, 3)"),
    "matrix dtype": (lambda: BitChannel(Toy(), topology=np.zeros((3, 3))), "dtype float64"),
    "matrix self": (lambda: BitChannel(Toy(), topology=np.eye(3, dtype=bool)), "[0, 0] True"),
    "fixed unknown": (lambda: BitChannel(Toy(), fixed_actions={"z": 0}), "fixed_actions='z'"),
    "fixed outside": (lambda: BitChannel(Toy(), fixed_actions={"a": 3}), "fixed_actions['a']=3"),
    # an unbounded Box contains inf, and 1e39 overflowed float32 to it: the env was sent inf
    "fixed beyond float32": (
        lambda: BitChannel(
            Toy(action_space=spaces.Box(-np.inf, np.inf, (2,), np.float32)), fixed_actions={"a": [0.5, 1e39]}
        ),
        "fixed_actions['a']=[0.5, 1e+39]: must be a finite action of Box(",
    ),  # fmt: skip
    "fixed inf": (
        lambda: BitChannel(
            Toy(action_space=spaces.Box(-np.inf, np.inf, (1,), np.float32)), fixed_actions={"a": [float("inf")]}
        ),
        "must be a finite action",
    ),  # fmt: skip
    "reset seed -1": (lambda: BitChannel(Toy()).reset(seed=-1), "seed=-1"),  # was numpy's, naming no seed
    "reset seed text": (lambda: BitChannel(Toy()).reset(seed="7"), "seed='7'"),  # type: ignore[arg-type]
}


@pytest.mark.parametrize("case", BAD)
def test_bad_input_gets_one_line(case: str) -> None:
    build, names = BAD[case]
    with pytest.raises(ConfigError) as err:
        build()
    message = str(err.value)
    assert "\n" not in message and names in message, message
