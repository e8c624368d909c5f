"""The PettingZoo view: PettingZoo's own conformance tests, and agreement with the vectorized env."""

from __future__ import annotations

import json
import warnings
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs import goal_exchange_v0
from bitcomm.envs.vec import Observation, VecGoalExchange
from bitcomm.errors import ConfigError
from bitcomm.policies.reference import OraclePolicy

CONFIGS: dict[str, dict[str, Any]] = {
    "default": {},
    "noisy-3-agents": dict(
        n_agents=3, delay=2, flip_prob=0.1, drop_prob=0.2, act_fail_prob=0.1, act_delay=1, size=6, max_steps=50
    ),
    "multi-recipient": dict(n_agents=3, recipients=[[1, 2], [2], [0]], observes=[1, 2, 0], bits=5),
}


@pytest.mark.parametrize("name", CONFIGS)
def test_parallel_api(name: str) -> None:
    env = goal_exchange_v0.parallel_env(**CONFIGS[name])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo reports soft failures as warnings
        parallel_api_test(env, num_cycles=300)


@pytest.mark.parametrize("name", CONFIGS)
def test_parallel_seed(name: str) -> None:
    parallel_seed_test(lambda: goal_exchange_v0.parallel_env(**CONFIGS[name]), num_cycles=300)


def test_aec_api() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # style hints about Dict spaces, not failures
        api_test(goal_exchange_v0.env(), num_cycles=300)


def test_spaces() -> None:
    env = goal_exchange_v0.parallel_env(size=6, n_agents=3, bits=5, recipients=[[1, 2], [2], [0]], observes=[1, 2, 0])
    assert env.possible_agents == ["agent_0", "agent_1", "agent_2"]
    act = env.action_space("agent_1")
    assert isinstance(act, spaces.Dict)
    assert act["move"] == spaces.Discrete(5) and act["message"] == spaces.MultiBinary(5)
    obs_space = env.observation_space("agent_1")
    assert obs_space["planes"].shape == (2, 6, 6) and obs_space["planes"].dtype == np.uint8
    assert obs_space["received"].shape == (2, 5) and obs_space["received"].dtype == np.uint8  # agent 2 hears two
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(infos) == set(env.possible_agents)
    for agent, o in obs.items():
        assert env.observation_space(agent).contains(o)
    assert env.state().shape == env.state_space.shape == (6, 6, 6)


def test_bad_values_raise_config_error() -> None:
    bad: list[dict[str, Any]] = [
        dict(size=1),
        dict(n_agents=1),
        dict(observes=[0, 1]),
        dict(delay=0),
        dict(flip_prob=2.0),
        dict(render_mode="human"),
    ]
    for kwargs in bad:
        with pytest.raises(ConfigError):
            goal_exchange_v0.parallel_env(**kwargs)
    with pytest.raises(ConfigError, match="invalid seed=-1"):  # numpy's own error named no parameter
        goal_exchange_v0.parallel_env().reset(seed=-1)


def test_numpy_numbers_are_taken_wherever_python_ones_are() -> None:
    """`size=np.int64(4)` was refused ("must be an integer"); the task then holds plain Python numbers."""
    env = goal_exchange_v0.parallel_env(
        size=np.int64(4),
        n_agents=np.int32(3),
        max_steps=np.uint16(20),
        observes=np.array([1, 2, 0]),
        act_fail_prob=np.float32(0.5),
        act_delay=np.int8(1),
        bits=np.int64(5),
        recipients=np.array([[1], [2], [0]]),
        delay=np.int64(2),
        flip_prob=np.int64(0),
        drop_prob=np.float64(0.25),
    )
    plain = goal_exchange_v0.parallel_env(
        size=4, n_agents=3, max_steps=20, observes=[1, 2, 0], act_fail_prob=0.5, act_delay=1, bits=5,
        recipients=[[1], [2], [0]], delay=2, flip_prob=0, drop_prob=0.25,
    )  # fmt: skip
    assert env.task == plain.task
    assert TaskConfig.from_dict(json.loads(json.dumps(env.task.to_dict()))) == env.task  # plain numbers: JSON
    assert type(env.task.env.size) is int and type(env.task.channel.bits) is int
    with pytest.raises(ConfigError, match=r"invalid size=True: must be an integer"):
        goal_exchange_v0.parallel_env(size=True)
    with pytest.raises(ConfigError, match=r"invalid size=np.int64\(1\): must be an integer in \[2, 1024\]"):
        goal_exchange_v0.parallel_env(size=np.int64(1))
    with pytest.raises(ConfigError, match=r"invalid size=np.float64\(4.0\)"):
        goal_exchange_v0.parallel_env(size=np.float64(4.0))


def observation_of(obs: dict[str, dict[str, np.ndarray]], agents: list[str], t: int) -> Observation:
    """The per-agent dicts stacked into the batch-of-one `Observation` a vectorized policy reads."""
    planes = np.stack([obs[a]["planes"] for a in agents])[None]
    received = np.stack([obs[a]["received"] for a in agents])[None]
    return Observation(planes, received, np.zeros((1, 0, 0, 0), np.uint8), np.array([t]))


@pytest.mark.parametrize("kwargs", [{}, dict(n_agents=3, delay=2), dict(delay=3, size=7)])
def test_oracle_episode_matches_the_vectorized_env(kwargs: dict[str, Any]) -> None:
    """Same seed, same policy: the ParallelEnv and VecGoalExchange play the very same episode."""
    env_kw = {k: v for k, v in kwargs.items() if k in ("n_agents", "size")}
    ch_kw = {k: v for k, v in kwargs.items() if k == "delay"}
    task = TaskConfig(EnvConfig(**env_kw), ChannelConfig(**ch_kw))
    oracle = OraclePolicy(task)
    for seed in range(5):
        vec = VecGoalExchange(task, 1, seed=seed)
        vec_rewards = []
        while True:
            moves, bits = oracle(vec.observe())
            result, _ = vec.step(moves, bits)
            vec_rewards.append(result.rewards[0].copy())
            if result.finished.env_index.size:
                vec_length = int(result.finished.length[0])
                break

        env = goal_exchange_v0.parallel_env(**kwargs)
        obs, _ = env.reset(seed=seed)
        agents, t, pz_rewards = env.possible_agents, 0, []
        while env.agents:
            moves, bits = oracle(observation_of(obs, agents, t))
            actions = {a: {"move": moves[0, i], "message": bits[0, i]} for i, a in enumerate(agents)}
            obs, rewards, terms, truncs, infos = env.step(actions)
            pz_rewards.append([rewards[a] for a in agents])
            t += 1
        assert t == vec_length
        assert all(terms.values()) and not any(truncs.values())
        np.testing.assert_allclose(pz_rewards, vec_rewards, atol=1e-6)
        assert infos["agent_0"]["team_reward"] == pytest.approx(sum(pz_rewards[-1]), abs=1e-6)
        # the terminal observation shows every agent on its goal
        state = env.state()
        n = len(agents)
        np.testing.assert_array_equal(state[:n], state[n:])


def test_reset_seed_is_deterministic_and_episode_end_empties_agents() -> None:
    env = goal_exchange_v0.parallel_env(max_steps=4)
    first, _ = env.reset(seed=3)
    stay = {a: {"move": 0, "message": np.zeros(7, np.int8)} for a in env.possible_agents}
    for _ in range(4):
        assert env.agents == env.possible_agents
        _, rewards, terms, truncs, _ = env.step(stay)
    assert env.agents == [] and all(truncs.values()) and not any(terms.values())
    with pytest.raises(RuntimeError):
        env.step(stay)
    again, _ = env.reset(seed=3)
    for a in env.possible_agents:
        np.testing.assert_array_equal(first[a]["planes"], again[a]["planes"])
    unseeded, _ = env.reset()  # goes on with the stream: a new episode, with no messages in flight
    assert env.agents == env.possible_agents
    assert not any(o["received"].any() for o in unseeded.values())


def test_messages_and_drops_reach_the_infos() -> None:
    env = goal_exchange_v0.parallel_env(drop_prob=1.0, delay=1)
    env.reset(seed=0)
    ones = {a: {"move": 0, "message": np.ones(7, np.int8)} for a in env.possible_agents}
    obs, _, _, _, infos = env.step(ones)
    assert all(info["dropped"] for info in infos.values())
    assert not any(o["received"].any() for o in obs.values())

    env = goal_exchange_v0.parallel_env(delay=1)
    env.reset(seed=0)
    sent = {"agent_0": {"move": 0, "message": np.array([1, 0, 0, 0, 0, 0, 1])}, "agent_1": ones["agent_1"]}
    obs, _, _, _, infos = env.step(sent)
    assert not any(info["dropped"] for info in infos.values())
    np.testing.assert_array_equal(obs["agent_1"]["received"], [[1, 0, 0, 0, 0, 0, 1]])
    np.testing.assert_array_equal(obs["agent_0"]["received"], [[1] * 7])


def test_bad_actions_are_refused() -> None:
    env = goal_exchange_v0.parallel_env()
    env.reset(seed=0)
    good = {"move": 0, "message": np.zeros(7, np.int8)}
    with pytest.raises(KeyError):
        env.step({"agent_0": good})
    with pytest.raises(ValueError, match="move"):
        env.step({"agent_0": good, "agent_1": {"move": 5, "message": np.zeros(7)}})
    with pytest.raises(ValueError, match="message"):
        env.step({"agent_0": good, "agent_1": {"move": 0, "message": np.zeros(6)}})


def one_line_refusal(env: Any, actions: Any) -> str:
    """The ConfigError `env.step(actions)` raises, checked to be one line; the episode has not moved on."""
    state = env.state()
    with pytest.raises(ConfigError) as err:
        env.step(actions)
    message = str(err.value)
    assert message.startswith("invalid ") and "\n" not in message, message
    np.testing.assert_array_equal(env.state(), state)
    assert env.agents == env.possible_agents
    return message


@pytest.mark.parametrize(
    ("move", "shown"),
    [
        (2.5, "2.5"),  # was truncated to 2
        (2.0, "2.0"),  # a float, even a whole one: Discrete(5) does not hold it either
        (np.float64(1.0), "np.float64(1.0)"),
        (True, "True"),  # was move 1
        (np.bool_(False), "np.False_"),
        (np.array(True), "array(True)"),
        (np.array([2]), "array([2])"),
        ("2", "'2'"),
        (-1, "-1"),
        (np.int64(5), "np.int64(5)"),
        (None, "None"),
    ],
)
def test_a_move_must_be_an_integer_in_range(move: Any, shown: str) -> None:
    env = goal_exchange_v0.parallel_env()
    env.reset(seed=0)
    good = {"move": 0, "message": np.zeros(7, np.int8)}
    message = one_line_refusal(env, {"agent_0": good, "agent_1": {"move": move, "message": np.zeros(7, np.int8)}})
    assert message == f"invalid actions['agent_1']['move']={shown}: must be an integer in [0, 5)"


def test_actions_for_unknown_agents_and_malformed_actions_are_refused() -> None:
    env = goal_exchange_v0.parallel_env(bits=30)
    env.reset(seed=0)
    good = {"move": 0, "message": np.zeros(30, np.int8)}
    both = {"agent_0": good, "agent_1": good}
    # an action for an agent that is not live (was ignored), named with the live agents
    message = one_line_refusal(env, {**both, "agent_9": good})
    assert message == "invalid agent='agent_9': actions are for live agents only: ['agent_0', 'agent_1']"
    assert "invalid agent=0" in one_line_refusal(env, {**both, 0: good})
    # an action dict with a key other than 'move' and 'message' (was ignored), or without one of them
    message = one_line_refusal(env, {**both, "agent_0": {**good, "speak": 1}})
    assert message.startswith("invalid actions['agent_0']: has the keys 'message', 'move', 'speak';")
    assert "has the keys 'move';" in one_line_refusal(env, {**both, "agent_1": {"move": 0}})
    assert "actions['agent_1']=3: must be a dict" in one_line_refusal(env, {**both, "agent_1": 3})
    assert "invalid actions=[" in one_line_refusal(env, [good, good])
    # a long message keeps its repr on one line
    message = one_line_refusal(env, {**both, "agent_1": {"move": 0, "message": np.full(30, 2)}})
    assert message.startswith("invalid actions['agent_1']['message']=array([2, 2,") and "must be 30 bits" in message
    # a missing live agent is still a KeyError, as before
    with pytest.raises(KeyError, match="agent_1"):
        env.step({"agent_0": good})


def test_every_action_the_action_space_holds_is_taken() -> None:
    """What `action_space(agent).sample()` gives, and the other integers `Discrete(5)` holds (Python and numpy
    integers, 0-d integer arrays) with messages `MultiBinary(K)` holds."""
    env = goal_exchange_v0.parallel_env(max_steps=50)
    env.reset(seed=0)
    space = env.action_space("agent_0")
    moves = [3, np.int64(4), np.uint8(1), np.int32(2), np.array(3), np.array(0, np.uint8)]
    messages = [np.ones(7, np.int8), [0, 1, 0, 1, 0, 1, 0], np.zeros(7, bool), np.ones(7)]
    for move, message in zip(moves, messages * 2, strict=False):
        action = {"move": move, "message": message}
        assert space.contains({"move": move, "message": np.asarray(message)})
        env.step({"agent_0": action, "agent_1": env.action_space("agent_1").sample()})
    for _ in range(20):
        if not env.agents:
            env.reset()
        env.step({a: env.action_space(a).sample() for a in env.agents})


def test_render_ansi() -> None:
    env = goal_exchange_v0.parallel_env(size=4, render_mode="ansi")
    env.reset(seed=0)
    text = env.render()
    assert isinstance(text, str)
    rows = text.splitlines()
    assert len(rows) == 4 and all(len(r.split()) == 4 for r in rows)
