"""`bitcomm.EnvController`: a policy trained on a wrapped env, acting in its user's own loop on a hand-stepped
`BitChannel`, acts as training and evaluation do (the same inputs, network call, clipping and sampling stream).

The toy envs are test_env_learning's: `SignalEnv` (a speaker that may leave after step 0, Discrete or Box actions)
and `SpacesEnv` (Dict observations, MultiDiscrete actions, checked to be in their space on arrival).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import bitcomm
from bitcomm.checkpoint import save_checkpoint
from bitcomm.envs.vector import inner_action
from bitcomm.errors import ConfigError
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.learn.env_controller import EnvController
from bitcomm.learn.env_eval import chunk_seed, evaluate_env
from bitcomm.learn.env_rollout import EnvRollout, batch_seeds, make_vec, play
from bitcomm.learn.env_run import train_env
from bitcomm.policies.controller import Controller
from bitcomm.policies.mlp import MlpPolicy
from test_env_learning import SPEC, CountedEnv, config

MODULE = SPEC.split(":")[0]  # the toy envs' module, as the run records it


def by_hand(controller: EnvController, env: Any, seed: int, greedy: bool) -> tuple[list[dict], float, int]:
    """One episode as a user's loop plays it: each step's observations, exactly as the env returned them (an agent
    that just left included), into `act`, its answer into `step`. The joint actions sent, return and length."""
    observations, _ = env.reset(seed=seed)
    sent, team_return, length = [], 0.0, 0
    while env.agents:
        present = list(env.agents)
        joint = controller.act(observations, greedy=greedy)
        sent.append({a: joint[a] for a in present})
        observations, rewards, *_ = env.step(joint)
        team_return += float(np.mean([rewards[a] for a in present], dtype=np.float32))
        length += 1
    return sent, team_return, length


def assert_same_episode(
    controller: EnvController, ro: EnvRollout, b: int, sent: list[dict], ret: float, n: int, rtol: float = 0.0
) -> None:
    """Copy b of the vectorized rollout and the hand-played episode: same length and return, and at every step
    each present agent's action (in the inner env's space, Box clipped) and message. Box actions within `rtol`:
    the network's matrix products over B copies and over one may round differently in the last bit."""
    L = controller.layout
    assert (n, ret) == (int(ro.length[b]), pytest.approx(float(ro.team_return[b]), abs=1e-5))
    for t, joint in enumerate(sent):
        present = [(i, a) for i, a in enumerate(L.agents) if ro.alive[t, b, i]]
        assert sorted(joint) == sorted(a for _, a in present), t
        for i, a in present:
            vec_action = ro.actions[t, b, i].numpy()
            if not L.discrete:
                vec_action = np.clip(vec_action, L.low[i], L.high[i])
            want = inner_action(L.action_spaces[i], vec_action)
            np.testing.assert_allclose(joint[a]["action"], want, rtol=rtol, atol=0, err_msg=f"step {t}, {a}")
            np.testing.assert_array_equal(joint[a]["message"], ro.bits[t, b, i].numpy(), err_msg=f"step {t}, {a}")


# ---------------------------------------------------------------------------------------------- same as evaluation
VARIANTS = {
    "discrete, the speaker leaves": ({"env_kwargs": {"steps": 4, "speaker_leaves": True}}, "bitwise"),
    "box, clipped": ({"env_kwargs": {"steps": 3, "box": True}}, "onehot"),
    "dict observations, multidiscrete actions": (
        {"env": f"{MODULE}:SpacesEnv", "env_kwargs": {"obs": "dict", "act": "multidiscrete"}},
        "bitwise",
    ),
}


def random_controller(cfg: EnvTrainConfig, messages: str, seed: int) -> EnvController:
    """A policy far from uniform (weights of scale 1), with observation statistics far from (0, 1), so that a
    controller reading other inputs, skipping the normalisation or the clipping, or sampling otherwise acts
    differently."""
    with make_vec(cfg, 1) as vec:
        layout = vec.layout
    torch.manual_seed(seed)
    policy = MlpPolicy(layout, messages, (16,), obs_norm=True)
    with torch.no_grad():
        for p in policy.parameters():
            p.normal_(0.0, 1.5)
        policy.obs_norm.mean.normal_(0.0, 0.5)
        policy.obs_norm.var.uniform_(0.05, 2.0)
    return EnvController(policy, dataclasses.replace(cfg, messages=messages), seed=seed)


@pytest.mark.parametrize("variant", VARIANTS)
def test_greedy_play_in_your_own_loop_is_the_vectorized_evaluation_step_by_step(variant: str) -> None:
    kwargs, messages = VARIANTS[variant]
    cfg = config(**kwargs)
    controller = random_controller(cfg, messages, seed=3)
    B = 6
    with make_vec(cfg, B) as vec:
        ro = play(vec, controller.policy, chunk_seed(11, 0), None, greedy=True)
    assert ro.length.min() >= 2 and (variant != "box, clipped" or (ro.actions.abs() > 1).any())  # clipping matters
    for b, env_seed in enumerate(batch_seeds(chunk_seed(11, 0), B)):
        env = controller.make_env()
        assert_same_episode(controller, ro, b, *by_hand(controller, env, int(env_seed), greedy=True), rtol=1e-5)
        env.close()


@pytest.mark.parametrize("variant", VARIANTS)
def test_sampled_play_in_your_own_loop_draws_what_evaluation_draws(variant: str) -> None:
    """One copy, the controller's generator seeded as evaluation's: the same draws, step after step, so the same
    episode; over several episodes in a row, too (the generator goes on)."""
    kwargs, messages = VARIANTS[variant]
    cfg = config(**kwargs)
    controller = random_controller(cfg, messages, seed=5)
    generator = torch.Generator().manual_seed(5)
    env = controller.make_env()
    with make_vec(cfg, 1) as vec:
        for episode in range(3):
            ro = play(vec, controller.policy, chunk_seed(5, episode), generator)
            env_seed = int(batch_seeds(chunk_seed(5, episode), 1)[0])
            assert_same_episode(controller, ro, 0, *by_hand(controller, env, env_seed, greedy=False))
    env.close()


def test_a_trained_run_loaded_acts_as_evaluate_env_measures(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Loaded from the run folder (its observation statistics with it): an episode played by hand on the env
    seeded as `evaluate_env`'s first copy is that episode, sampled and greedy."""
    monkeypatch.setenv("BITCOMM_TRUST_ENVS", MODULE)
    cfg = config(env_kwargs={"steps": 3, "speaker_leaves": True}, obs_norm=True, lr=0.05)
    path = train_env(cfg, tmp_path / "run", progress=False)
    for seed in range(4):
        for greedy in (False, True):
            controller = EnvController.load(tmp_path / "run", seed=seed)
            assert float(controller.policy.obs_norm.count.max()) > 0  # the saved statistics, not fresh ones
            env = controller.make_env()
            _, ret, length = by_hand(controller, env, int(batch_seeds(chunk_seed(seed, 0), 1)[0]), greedy)
            env.close()
            result = evaluate_env(path, 1, seed=seed, greedy=greedy)
            assert (ret, length) == (pytest.approx(result.mean_team_return), result.mean_episode_length)


def test_it_is_a_public_name() -> None:
    assert bitcomm.EnvController is EnvController and "EnvController" in bitcomm.__all__


# ---------------------------------------------------------------------------------------------- loading
@pytest.fixture(scope="module")
def counted_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("counted") / "run"
    train_env(config(env=f"{MODULE}:CountedEnv", episodes=8), run, progress=False)
    return run


def test_training_leaves_the_callers_torch_generator_as_it_was(tmp_path: Path) -> None:
    """A notebook's own draws after `train_env` are those it would have made without it (the run seeds torch)."""
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    train_env(config(env=f"{MODULE}:CountedEnv", episodes=8), tmp_path / "run", progress=False)
    assert torch.equal(torch.rand(3), expected)


def test_loading_a_run_leaves_the_callers_torch_generator_as_it_was(counted_run: Path) -> None:
    """`EnvController.load` (and `evaluate_env`, which loads) built the network's random initial weights from torch's
    global generator before reading the trained ones over them, moving a notebook's draws on."""
    typed = f"{MODULE}:CountedEnv"
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    EnvController.load(counted_run, typed_env=typed)
    evaluate_env(counted_run, 2, seed=0, typed_env=typed)
    assert torch.equal(torch.rand(3), expected)


def test_an_episode_count_or_seed_evaluation_cannot_play_is_one_line(counted_run: Path) -> None:
    """0 episodes were an IndexError from an empty batch, a negative seed numpy's "expected non-negative integer"
    (the grid's `evaluate` and `bitcomm eval` named both already)."""
    typed = f"{MODULE}:CountedEnv"
    for episodes, seed, line in ((0, 0, "invalid episodes=0: must be an integer >= 1"), (2, -1, "invalid seed=-1")):
        with pytest.raises(ConfigError, match=line):
            evaluate_env(counted_run, episodes, seed=seed, typed_env=typed)
    with pytest.raises(ConfigError, match="invalid seed=-1"):
        EnvController.load(counted_run, typed_env=typed, seed=-1)


def test_a_numpy_seed_evaluates_and_samples_as_the_python_one(counted_run: Path) -> None:
    """torch's `manual_seed` refuses a numpy integer ("an integer is required"), which `check_seed` takes."""
    typed = f"{MODULE}:CountedEnv"
    seeded = EnvController.load(counted_run, typed_env=typed, seed=np.int64(3)).generator.get_state()
    assert torch.equal(seeded, torch.Generator().manual_seed(3).get_state())
    played = evaluate_env(counted_run, 2, seed=np.int64(3), typed_env=typed)
    assert played == evaluate_env(counted_run, 2, seed=3, typed_env=typed)


def test_a_greedy_or_generator_of_the_wrong_kind_is_one_line() -> None:
    """`greedy="False"` is a truthy string: taken, it played greedily; a generator that is not a torch one was torch's
    TypeError from deep in its sampling."""
    controller = random_controller(config(), "bitwise", seed=0)
    env = controller.make_env()
    observations, _ = env.reset(seed=0)
    with pytest.raises(ConfigError, match="invalid greedy='False': must be True or False"):
        controller.act(observations, greedy="False")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="invalid generator=5: must be a torch.Generator"):
        controller.act(observations, generator=5)  # type: ignore[arg-type]
    env.close()


def test_loading_builds_one_env_copy_and_closes_it(counted_run: Path) -> None:
    CountedEnv.made.clear()
    EnvController.load(counted_run, typed_env=f"{MODULE}:CountedEnv")
    assert len(CountedEnv.made) == 1 and CountedEnv.made[0].closed


def test_loading_a_run_builds_its_env_only_if_you_vouch_for_it(
    counted_run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same rule as evaluate_env: the spec typed (`typed_env`), or its package in BITCOMM_TRUST_ENVS."""
    monkeypatch.delenv("BITCOMM_TRUST_ENVS", raising=False)
    CountedEnv.made.clear()
    with pytest.raises(ConfigError) as err:
        EnvController.load(counted_run)
    assert "\n" not in str(err.value) and f"invalid env='{MODULE}:CountedEnv'" in str(err.value)
    assert "BITCOMM_TRUST_ENVS" in str(err.value) and not CountedEnv.made  # refused before anything was built
    assert f"typed_env='{MODULE}:CountedEnv'" in str(err.value)  # what a Python caller types: not --env
    with pytest.raises(ConfigError):
        EnvController.load(counted_run, typed_env=f"{MODULE}:SignalEnv")  # another spec vouches for nothing
    monkeypatch.setenv("BITCOMM_TRUST_ENVS", MODULE)
    assert EnvController.load(counted_run).layout.agents == ("speaker", "listener")


def test_a_grid_run_and_a_wrapped_env_run_each_name_their_reader(tmp_path: Path, counted_run: Path) -> None:
    grid = tmp_path / "grid"
    save_checkpoint(grid, {"task": {}}, {"policy": {"w": torch.zeros(1)}}, 16, 1, {})
    with pytest.raises(ConfigError) as err:
        EnvController.load(grid)
    assert str(err.value) == (
        f"invalid checkpoint='{grid / 'checkpoints' / 'ckpt_000000016.safetensors'}': trained on the grid task, not "
        "on a wrapped env; bitcomm.Controller acts with it (bitcomm eval and bitcomm render read both)"
    )
    with pytest.raises(ConfigError) as err:
        Controller.load(counted_run)
    assert "\n" not in str(err.value) and f"trained on a wrapped env ({MODULE}:CountedEnv)" in str(err.value)
    assert "bitcomm.EnvController" in str(err.value)


# ---------------------------------------------------------------------------------------------- bad input
GOOD = {"observation": np.array([0.5, 0.5, 0.0], np.float32), "messages": np.zeros((1, 2), np.int8)}


@pytest.mark.parametrize(
    ("observations", "line"),
    [
        ([GOOD], "invalid observations='list': must be a dict agent -> observation, as BitChannel's reset and step"),
        ({"ghost": GOOD}, "invalid agent='ghost': the run's env has agents ['speaker', 'listener']"),
        ({"listener": GOOD["observation"]}, "invalid observations['listener']='ndarray': must be a dict with"),
        (
            {"listener": {"observation": GOOD["observation"]}},
            "invalid observations['listener']=['observation']: must be a dict with 'observation' and 'messages' "
            "(as BitChannel returns); 'messages' is missing",
        ),
        (
            {"listener": {**GOOD, "messages": np.zeros(2)}},
            "invalid observations['listener']['messages'] shape=(2,): must be (1, 2) (slots, bits per message)",
        ),
        ({"listener": {**GOOD, "messages": np.full((1, 2), 0.5)}}, "['messages']=0.5: every bit must be 0 or 1"),
        (
            {"listener": {**GOOD, "observation": np.zeros(2)}},
            "invalid observations['listener']['observation'] shape=(2,): must fit Box(0.0, 1.0, (3,), float32) "
            "(3 numbers once flattened, not 2)",
        ),
        ({"speaker": {**GOOD, "observation": "high"}}, "invalid observations['speaker']['observation']"),
        (
            {"listener": {**GOOD, "observation": np.array([0.5, np.nan, 0.0], np.float32)}},
            "invalid observations['listener']['observation']=nan: the env's observations must be finite numbers",
        ),
    ],
)
def test_an_observation_a_bitchannel_would_not_give_is_one_line(observations: Any, line: str) -> None:
    controller = random_controller(config(), "bitwise", seed=0)
    with pytest.raises(ConfigError) as err:
        controller.act(observations)
    assert "\n" not in str(err.value) and line in str(err.value), err.value


def test_no_agent_present_is_no_action_and_no_draw() -> None:
    controller = random_controller(config(), "bitwise", seed=0)
    state = controller.generator.get_state()
    assert controller.act({}) == {} and torch.equal(controller.generator.get_state(), state)
