"""A training run on a wrapped PettingZoo env: the grid's synchronous trainer (`run.py`) for `EnvTrainConfig`.

It writes the same run folder (`bitcomm.learn.run_folder`: config.json with versions and git commit,
metrics.csv, TensorBoard, the learning curve of the team return, atomic resumable checkpoints) under the
folder's lock. Batch k plays `num_envs` first episodes whose env seeds come from
`SeedSequence(seed, spawn_key=(k,))`; weights start under `torch.manual_seed(seed)`; sampling and
minibatch order come from one generator seeded with `seed`, whose state is checkpointed. So a run is
reproducible on one machine, and a resumed run continues as if it had never stopped; with `env_workers` the
env copies are stepped in worker processes, which changes no episode.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.checkpoint import is_env_config, read_config, resolve
from bitcomm.errors import ConfigError
from bitcomm.learn.allocator import keep_freed_memory
from bitcomm.learn.beside import critic_beside_policy
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.learn.env_learner import EnvLearner
from bitcomm.learn.env_rollout import make_vec, play
from bitcomm.learn.run_folder import (
    RESUMES,
    Logger,
    Progress,
    check_start,
    config_of,
    finite_or_stop,
    prepare,
    read_json_object,
    restore_learner,
    run_folder,
    save_learner,
    stopped,
    stops_in_one_line,
    train_batches,
    write_config,
)
from bitcomm.policies.denormals import flush_denormals
from bitcomm.run_lock import run_lock


def train_env(cfg: EnvTrainConfig, out: str | Path, resume: bool = False, progress: bool = True) -> Path:
    """Train until `cfg.episodes` episodes are played (whole batches); returns the latest checkpoint."""
    out = run_folder(out)
    keep_freed_memory()
    check_start(out, resume)
    # refuses a bad env or channel before the folder is touched; closed (its workers stopped) however the run ends
    with make_vec(cfg, cfg.num_envs, workers=cfg.env_workers) as vec:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(
                f"invalid out={str(out)!r}: cannot create the run folder ({err.strerror or err})"
            ) from None
        # the run seeds torch's global generator (weights, noise that may draw from it); the caller's comes back after
        with run_lock(out), flush_denormals(), stops_in_one_line(out), torch.random.fork_rng(devices=[]):
            return _train(cfg, vec, out, resume, progress)


def _train(cfg: EnvTrainConfig, vec: Any, out: Path, resume: bool, progress: bool) -> Path:
    cfg, saved = prepare(cfg, out, resume)
    torch.manual_seed(cfg.seed)
    learner = EnvLearner(cfg, vec.layout)
    generator = torch.Generator().manual_seed(cfg.seed)
    prog = Progress()
    if saved is not None:
        restore_learner(learner, saved)
        generator.set_state(saved["generator"])
        torch.set_rng_state(saved["torch_rng"])
        prog.restore(saved)
    write_config(cfg, out, saved)
    logger = Logger(out, prog.batches if saved is not None else None)

    def play_and_learn() -> dict[str, Any]:
        t0 = time.perf_counter()
        rng = generator.get_state(), torch.get_rng_state()
        try:  # rollout: batch k's episodes are fixed by (seed, k)
            seed = np.random.SeedSequence(cfg.seed, spawn_key=(prog.batches,))
            ro = play(vec, learner.policy, seed, generator, learning=True)
        except (Exception, KeyboardInterrupt) as err:  # a worker died (`WorkerDied`), the env gave what it may not
            if not prog.batches:  # (a NaN reward...) or its own code raised, or Ctrl-C came again; nothing learned
                raise  # yet: no checkpoint, so that the same command starts afresh
            # the learner is as the last batch left it: save that, as a stop signal would,
            generator.set_state(rng[0])  # and the draws as they were, so a resume plays this batch as it would have
            torch.set_rng_state(rng[1])
            if isinstance(err, KeyboardInterrupt):  # the second Ctrl-C, where the batch's episodes do not end (the
                # first asks for a stop after the batch): the batch is dropped, the batches before are kept
                raise stopped(signal.SIGINT, prog.episodes, save(None)) from None
            saved_as = f"saved after {prog.episodes} episodes as {save(None)}; {RESUMES}"
            if isinstance(err, ConfigError):
                raise ConfigError(f"{err}; {saved_as}") from None
            err.add_note(f"bitcomm: the env raised this while playing a batch; {saved_as}")  # its traceback is
            raise  # the env's own bug report: kept
        # update
        stats = learner.update(ro, generator)
        learner.policy.obs_norm.update(ro.obs, ro.alive)  # after the update: one batch, one set of statistics
        learner.critic.state_norm.update(ro.state, ro.valid)
        finite_or_stop(out, learner, prog.episodes + len(ro.length))
        prog.wall_s += time.perf_counter() - t0
        row = prog.add_batch(ro.length, ro.team_return, int(ro.alive.sum()))
        return {**row, "charts/team_return_rolling": float(np.mean(prog.recent_return)), **stats}

    def save(rank: float | None) -> Path:
        return save_learner(out, cfg, learner, generator, prog, metric="team_return", rank=rank)

    def postfix(row: dict[str, Any]) -> dict[str, str]:
        return {"ret": f"{row['charts/team_return_rolling']:.2f}"}

    with critic_beside_policy(learner, torch.get_num_threads()):
        return train_batches(cfg, prog, logger, play_and_learn, save, postfix, progress)


def env_run_config(path: Path | str) -> EnvTrainConfig | None:
    """The `EnvTrainConfig` of a run folder or checkpoint trained on a wrapped env; None for a grid run."""
    p = Path(path)
    if p.is_dir() and (p / "config.json").is_file():
        record = read_json_object(p / "config.json", "config")
        return config_of(p / "config.json", record, EnvTrainConfig.from_dict) if is_env_config(record) else None
    config = read_config(p)
    return config_of(resolve(p), config, EnvTrainConfig.from_dict) if is_env_config(config) else None
