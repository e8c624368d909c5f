"""Slow envs stepped in worker processes (`SubprocVecEnv`, `--env-workers`; issue 18): the same episodes as in
the learner's process, bit for bit, so the same run; bad worker counts are one line; a worker that dies is one
`ConfigError`, never a hang, and a run it stops saves what it had.

`RelayEnv` is test-local: the workers import it by its spec (`test_env_subproc:RelayEnv`), since a spawned
process starts with this process's `sys.path`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from bitcomm.checkpoint import load_weights
from bitcomm.cli import main
from bitcomm.envs.vector import VecEnv
from bitcomm.errors import ConfigError
from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
from bitcomm.learn.env_learner import EnvLearner
from bitcomm.learn.env_rollout import EnvRollout, make_vec, play
from bitcomm.learn.env_run import train_env
from bitcomm.learn.run_folder import RESUMES

SPEC = f"{__name__}:RelayEnv"
MPE = "mpe2.simple_speaker_listener_v4:parallel_env"
BROKEN = 666
TIMEOUT = 60  # seconds: a hang fails the test instead of stalling the suite


class RelayEnv(ParallelEnv):
    """Three agents with different observation sizes and a seeded episode: its length (2 to 5 steps), the step
    at which `c` leaves, and noisy rewards all come from `reset`'s seed. An episode seeded `BROKEN` raises."""

    metadata = {"name": "relay_v0"}

    def __init__(self) -> None:
        self.possible_agents = ["a", "b", "c"]
        self.agents: list[str] = []
        self._obs = {a: spaces.Box(-5, 5, (k,), np.float32) for a, k in (("a", 2), ("b", 3), ("c", 1))}

    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(3)

    def _observe(self) -> dict[str, np.ndarray]:
        return {a: self.rng.normal(size=self._obs[a].shape).astype(np.float32) for a in self.agents}

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.rng, self.broken = np.random.default_rng(seed), seed == BROKEN
        self.t, self.length, self.c_leaves = 0, int(self.rng.integers(2, 6)), int(self.rng.integers(1, 4))
        self.agents = list(self.possible_agents)
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if self.broken:
            raise ValueError("relay broke")
        self.t += 1
        acting = list(self.agents)
        rew = {a: float(actions[a]) + float(self.rng.normal()) for a in acting}
        trunc = {a: self.t >= self.length for a in acting}
        term = {a: a == "c" and self.t >= self.c_leaves for a in acting}
        self.agents = [a for a in acting if not (trunc[a] or term[a])]
        obs = self._observe()
        return {a: obs.get(a, np.zeros(self._obs[a].shape, np.float32)) for a in acting}, rew, term, trunc, {}


def config(**kw: Any) -> EnvTrainConfig:
    base: dict[str, Any] = dict(env=SPEC, num_envs=5, episodes=10, hidden=(16,), checkpoint_seconds=1e9)
    return EnvTrainConfig(**{"channel": EnvChannelConfig(bits=2, flip_prob=0.2, drop_prob=0.3), **base, **kw})


def within_timeout(fn: Any, *args: Any) -> Any:
    with ThreadPoolExecutor(1) as pool:
        return pool.submit(fn, *args).result(timeout=TIMEOUT)


@pytest.fixture(scope="module")
def relay() -> Iterator[tuple[EnvTrainConfig, VecEnv, VecEnv]]:
    """The relay's 5 copies in this process and over 2 workers (shares of 3 and 2), started once: a worker
    imports this module, torch included, which takes seconds."""
    cfg = config()
    with make_vec(cfg, cfg.num_envs) as here, make_vec(cfg, cfg.num_envs, workers=2) as there:
        yield cfg, here, there


def assert_same_rollouts(cfg: EnvTrainConfig, here: VecEnv, there: VecEnv) -> EnvRollout:
    assert there.layout.agents == here.layout.agents and there.layout.state_size == here.layout.state_size
    torch.manual_seed(0)
    policy = EnvLearner(cfg, here.layout).policy
    for batch in range(2):  # the second reset reuses the workers' copies
        a, b = (play(v, policy, np.random.SeedSequence(7, spawn_key=(batch,)), torch.Generator().manual_seed(batch))
                for v in (here, there))  # fmt: skip
        assert all(torch.equal(x, y) for x, y in zip(a[:12], b[:12], strict=True))
        np.testing.assert_array_equal(a.team_return, b.team_return)
        np.testing.assert_array_equal(a.length, b.length)
        assert not there.running.any()
    return a


# ---------------------------------------------------------------------------------------------- same episodes
def test_two_workers_play_the_relays_rollouts_bit_for_bit(relay: tuple[EnvTrainConfig, VecEnv, VecEnv]) -> None:
    ro = assert_same_rollouts(*relay)
    assert len(set(ro.length.tolist())) > 1 and not ro.alive[-1, :, 2].any()  # uneven episodes, c left


def test_two_workers_play_mpe2_speaker_listeners_rollouts_bit_for_bit() -> None:
    cfg = config(env=MPE, num_envs=4, channel=EnvChannelConfig(bits=3, flip_prob=0.1, drop_prob=0.2))
    with make_vec(cfg, cfg.num_envs) as here, make_vec(cfg, cfg.num_envs, workers=2) as there:
        assert_same_rollouts(cfg, here, there)


def test_a_run_with_workers_learns_the_same_weights(tmp_path: Path) -> None:
    cfg = config(env=MPE, num_envs=16, episodes=64, epochs=1, minibatches=2, channel=EnvChannelConfig(bits=2))
    runs = [train_env(dataclasses.replace(cfg, env_workers=w), tmp_path / f"w{w}", progress=False) for w in (0, 2)]
    (w0, _), (w2, info) = (load_weights(p) for p in runs)
    assert info["config"]["env_workers"] == 2 and w0.keys() == w2.keys() == {"policy", "critic"}
    assert all(torch.equal(w0[net][k], w2[net][k]) for net in w0 for k in w0[net])
    # where the copies are stepped changes no episode, so a resume may change it
    argv = ["train", "--resume", "--out", str(tmp_path / "w2"), "--episodes", "80", "--env-workers", "0"]
    assert main([*argv, "--quiet", "--eval-episodes", "0"]) == 0
    assert json.loads((tmp_path / "w2" / "config.json").read_text())["env_workers"] == 0


# ---------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("workers", [-1, 2.5, 6])
def test_bad_worker_counts_are_one_line(workers: Any) -> None:
    with pytest.raises(ConfigError, match=r"^invalid env-workers=") as err:
        config(env_workers=workers)  # num_envs 5
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("value", ["-1", "2.5", "9"])
def test_cli_refuses_bad_worker_counts_in_one_line(value: str, tmp_path: Path, capsys: Any) -> None:
    argv = ["train", "--env", SPEC, "--num-envs", "8", "--env-workers", value, "--out", str(tmp_path / "run")]
    code = main([*argv, "--quiet", "--eval-episodes", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "env-workers" in err[0], err
    assert main(["train", "--env-workers", "2", "--out", str(tmp_path / "grid")]) == 2  # only with --env


def test_an_old_config_without_env_workers_steps_in_process() -> None:
    d = config(env_workers=2).to_dict()
    del d["env_workers"]
    assert EnvTrainConfig.from_dict(d).env_workers == 0


# ---------------------------------------------------------------------------------------------- failures
def test_a_killed_worker_is_one_config_error_not_a_hang() -> None:
    cfg = config(env=MPE, num_envs=4)
    vec = make_vec(cfg, cfg.num_envs, workers=2)
    procs = list(vec.procs)
    try:
        vec.reset(np.arange(4))
        os.kill(procs[1].pid, signal.SIGKILL)
        with pytest.raises(ConfigError, match=rf"env worker 1 of 2 .*{MPE} died") as err:
            within_timeout(vec.step, np.zeros((4, 2), np.int64), np.zeros((4, 2, 2), np.uint8))
        assert "\n" not in str(err.value)
    finally:
        within_timeout(vec.close)
    assert not any(p.is_alive() for p in procs)


def test_workers_leave_the_stop_signals_to_the_learner_and_close_still_ends_them() -> None:
    """`timeout` and a scheduler signal the whole process group: the learner stops after its batch and saves it,
    so its workers must live to finish that batch (before, SIGTERM killed them: the batch was lost, and the run
    ended blaming the env, "env worker 0 of 1 ... died (exit code -15); --env-workers 0 ... shows its own error")."""
    cfg = config(env=MPE, num_envs=4)
    vec = make_vec(cfg, cfg.num_envs, workers=2)
    procs = list(vec.procs)
    try:
        vec.reset(np.arange(4))
        for proc in procs:
            os.kill(proc.pid, signal.SIGTERM)
            os.kill(proc.pid, signal.SIGINT)
        step = within_timeout(vec.step, np.zeros((4, 2), np.int64), np.zeros((4, 2, 2), np.uint8))
        assert len(step.ended) == 4 and all(p.is_alive() for p in procs)
    finally:
        within_timeout(vec.close)
    assert not any(p.is_alive() for p in procs)


def test_a_run_whose_worker_dies_saves_what_it_learned_and_resumes_as_if_never_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A worker killed mid-batch loses that batch, not every batch since the last checkpoint (`--checkpoint-seconds`,
    here never): the run saves its learner and generators as they were before the batch, so that a resume plays
    it as the run would have, and ends in one line."""
    from bitcomm.envs.subproc_vector import WorkerDied
    from bitcomm.learn import env_run

    cfg = config(episodes=20)  # 4 batches of 5
    whole = train_env(cfg, tmp_path / "whole", progress=False)
    calls = []

    def dies_in_batch_3(vec: VecEnv, policy: Any, seed: Any, generator: torch.Generator, **kw: Any) -> EnvRollout:
        calls.append(1)
        if len(calls) == 3:
            torch.rand(3, generator=generator), torch.rand(3)  # part of the batch was sampled
            raise WorkerDied("env worker 1 of 2 (pid 1) running relay died (exit code -9)")
        return play(vec, policy, seed, generator, **kw)

    monkeypatch.setattr(env_run, "play", dies_in_batch_3)
    with pytest.raises(
        ConfigError,
        match=r"died \(exit code -9\); saved after 10 episodes as .*" + re.escape(RESUMES),
    ):
        train_env(cfg, tmp_path / "died", progress=False)
    monkeypatch.setattr(env_run, "play", play)
    resumed = train_env(cfg, tmp_path / "died", resume=True, progress=False)
    (a, _), (b, _) = load_weights(whole), load_weights(resumed)
    assert all(torch.equal(a[net][k], b[net][k]) for net in a for k in a[net])


def test_an_env_error_in_a_worker_is_raised_with_its_traceback(relay: tuple[EnvTrainConfig, VecEnv, VecEnv]) -> None:
    _, _, there = relay
    actions, messages = np.zeros((5, 3), np.int64), np.zeros((5, 3, 2), np.uint8)
    there.reset([0, 1, 2, 3, BROKEN])  # the last copy, in worker 1, raises at its first step
    with pytest.raises(RuntimeError, match=r"(?s)env worker 1 of 2 .*ValueError: relay broke"):
        within_timeout(there.step, actions, messages)
    there.reset(np.arange(5))  # the worker lives on
    assert there.step(actions, messages).rewards.shape == (5, 3)
