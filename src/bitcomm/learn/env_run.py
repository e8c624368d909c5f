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

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.checkpoint import CHECKPOINTS, LATEST, load_weights, refuse_nonfinite
from bitcomm.errors import ConfigError
from bitcomm.learn.env_config import EnvTrainConfig, is_env_config
from bitcomm.learn.env_learner import EnvLearner
from bitcomm.learn.env_rollout import make_vec, play
from bitcomm.learn.run_folder import (
    Logger,
    Progress,
    has_checkpoint,
    learner_state,
    prepare,
    read_json_object,
    save_run_checkpoint,
    write_config,
)
from bitcomm.run_lock import run_lock


def train_env(cfg: EnvTrainConfig, out: Path, resume: bool = False, progress: bool = True) -> Path:
    """Train until `cfg.episodes` episodes are played (whole batches); returns the latest checkpoint."""
    out = Path(out)
    if resume and not has_checkpoint(out):
        raise ConfigError(f"invalid out={str(out)!r}: no checkpoint to resume from ({CHECKPOINTS}/{LATEST} missing)")
    # refuses a bad env or channel before the folder is touched; closed (its workers stopped) however the run ends
    with make_vec(cfg, cfg.num_envs, workers=cfg.env_workers) as vec:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(
                f"invalid out={str(out)!r}: cannot create the run folder ({err.strerror or err})"
            ) from None
        with run_lock(out):
            return _train(cfg, vec, out, resume, progress)


def _train(cfg: EnvTrainConfig, vec: Any, out: Path, resume: bool, progress: bool) -> Path:
    from tqdm import tqdm

    saved = prepare(cfg, out, resume)
    torch.manual_seed(cfg.seed)
    learner = EnvLearner(cfg, vec.layout)
    generator = torch.Generator().manual_seed(cfg.seed)
    prog = Progress()
    if saved is not None:
        learner.policy.load_state_dict(saved["weights"]["policy"])
        learner.critic.load_state_dict(saved["weights"]["critic"])
        learner.opt_policy.load_state_dict(saved["opt_policy"])
        learner.opt_critic.load_state_dict(saved["opt_critic"])
        generator.set_state(saved["generator"])
        torch.set_rng_state(saved["torch_rng"])
        prog.restore(saved)
    write_config(cfg, out, {})
    logger = Logger(out, prog.batches if saved is not None else None)

    def weights() -> dict[str, dict[str, torch.Tensor]]:
        return {"policy": learner.policy.state_dict(), "critic": learner.critic.state_dict()}

    def save() -> Path:
        state = {
            **prog.state(),
            **learner_state(learner, generator),
        }
        return save_run_checkpoint(out, cfg, weights(), prog, state, metric="team_return")

    planned = -(-cfg.episodes // cfg.num_envs) * cfg.num_envs
    bar = tqdm(total=planned, initial=prog.episodes, disable=not progress, unit="ep", dynamic_ncols=True)
    last_save = time.monotonic()
    try:
        while prog.episodes < cfg.episodes:
            t0 = time.perf_counter()
            # rollout: batch k's episodes are fixed by (seed, k)
            ro = play(vec, learner.policy, np.random.SeedSequence(cfg.seed, spawn_key=(prog.batches,)), generator)
            # update
            stats = learner.update(ro, generator)
            learner.policy.obs_norm.update(ro.obs, ro.alive)  # after the update: one batch, one set of statistics
            learner.critic.state_norm.update(ro.state, ro.valid)
            refuse_nonfinite(out, prog.episodes + len(ro.length), **weights())
            prog.wall_s += time.perf_counter() - t0
            row = prog.add_batch(ro.length, ro.team_return, int(ro.alive.sum()))
            row.update({"charts/team_return_rolling": float(np.mean(prog.recent_return)), **stats})
            logger.log(row)
            bar.update(len(ro.length))
            bar.set_postfix(ret=f"{row['charts/team_return_rolling']:.2f}")
            if time.monotonic() - last_save >= cfg.checkpoint_seconds and prog.episodes < cfg.episodes:
                save()
                last_save = time.monotonic()
        path = save()
    finally:
        bar.close()
        logger.close()
    return path


def env_run_config(path: Path | str) -> EnvTrainConfig | None:
    """The `EnvTrainConfig` of a run folder or checkpoint trained on a wrapped env; None for a grid run."""
    p = Path(path)
    if p.is_dir() and (p / "config.json").is_file():
        record = read_json_object(p / "config.json", "config")
        return EnvTrainConfig.from_dict(record) if is_env_config(record) else None
    _, info = load_weights(p)
    return EnvTrainConfig.from_dict(info["config"]) if is_env_config(info["config"]) else None


def resume_env_config(out: Path, episodes: int | None = None) -> EnvTrainConfig:
    """The config a wrapped-env run in `out` was started with, with a new budget if one is given."""
    _, info = load_weights(out)
    d = dict(info["config"])
    if episodes is not None:
        d["episodes"] = episodes
    return EnvTrainConfig.from_dict(d)
