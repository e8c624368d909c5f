"""A training run: `train` holds the run folder's lock (`bitcomm.learn.run_folder` describes the folder)
and trains in `cfg.mode`: `sync` here, `a3c` in `bitcomm.learn.a3c`; or on Ray (`cfg.backend`,
`bitcomm.learn.ray_backend`).

`sync` mode: batch k plays `num_envs` whole episodes seeded by `SeedSequence(seed, spawn_key=(k,))`
and makes one learner update; the weights are initialised under `torch.manual_seed(seed)` and all
sampling and minibatch order come from one generator seeded with `seed`; its state and the global torch
generator's (which training-time noise may draw from) are checkpointed.
So a run is reproducible bit for bit on one machine, and a resumed run continues exactly as if it
had never stopped.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.errors import ConfigError, bad_value, check_instance
from bitcomm.learn.allocator import keep_freed_memory
from bitcomm.learn.beside import critic_beside_policy
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.held_out import held_out
from bitcomm.learn.run_folder import (
    Logger,
    Progress,
    check_start,
    finite_or_stop,
    oracle_record,
    prepare,
    restore_learner,
    run_folder,
    save_learner,
    stops_in_one_line,
    train_batches,
    write_config,
)
from bitcomm.policies.denormals import flush_denormals
from bitcomm.run_lock import run_lock


# ---------------------------------------------------------------------------------------------- loop
def train(
    cfg: TrainConfig, out: str | Path, resume: bool = False, progress: bool = True, address: str | None = None
) -> Path:
    """Train in `cfg.mode` (or on Ray, at the cluster `address`) until `cfg.episodes` episodes are played;
    returns the latest checkpoint."""
    return train_checked(cfg, check_run(cfg, out, resume, address), resume, progress, address)


def check_run(cfg: TrainConfig, out: str | Path, resume: bool = False, address: str | None = None) -> Path:
    """What `train` refuses, in one line, before it makes the run folder; returns the folder. `bitcomm train` calls
    it before it prints the folder's name, then `train_checked`, so that a Ray address is probed once a run."""
    check_instance("cfg", cfg, TrainConfig, "a TrainConfig, e.g. bitcomm.learn.config.make_train_config()")
    out = run_folder(out)
    check_start(out, resume)
    if cfg.backend == "ray":
        from bitcomm.learn.ray_backend import check_ray

        check_ray(address, cfg.workers)  # before the folder is made: Ray itself waits minutes for a host not there
    elif address is not None:
        raise bad_value("address", address, f"only with backend='ray' (this config's is {cfg.backend!r})")
    return out


def train_checked(cfg: TrainConfig, out: Path, resume: bool, progress: bool, address: str | None) -> Path:
    """`train` once `check_run` has passed."""
    keep_freed_memory()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"invalid out={str(out)!r}: cannot create the run folder ({err.strerror or err})") from None
    # the run seeds torch's global generator (weights, and noise that may draw from it); the caller's comes back after
    with run_lock(out), flush_denormals(), stops_in_one_line(out), torch.random.fork_rng(devices=[]):
        if cfg.backend == "ray":
            from bitcomm.learn.ray_backend import train_ray

            return train_ray(cfg, out, resume=resume, progress=progress, address=address)
        if cfg.mode == "a3c":
            from bitcomm.learn.a3c import train_a3c

            return train_a3c(cfg, out, resume=resume, progress=progress)
        return train_sync(cfg, out, resume=resume, progress=progress)


def train_sync(cfg: TrainConfig, out: Path, resume: bool = False, progress: bool = True) -> Path:
    from bitcomm.learn.learner import Learner
    from bitcomm.learn.rollout import Collector

    cfg, saved = prepare(cfg, out, resume)
    torch.manual_seed(cfg.seed)
    learner = Learner(cfg)
    generator = torch.Generator().manual_seed(cfg.seed)
    collector = Collector(cfg.training_task, cfg.num_envs)
    prog = Progress()
    if saved is not None:
        restore_learner(learner, saved)
        generator.set_state(saved["generator"])
        torch.set_rng_state(saved["torch_rng"])  # anything drawing from the global generator continues too
        prog.restore(saved)
    write_config(cfg, out, saved, oracle_record)
    logger = Logger(out, prog.batches if saved is not None else None)
    n = cfg.task.env.n_agents

    def play_and_learn() -> dict[str, Any]:
        t0 = time.perf_counter()
        # rollout: batch k's episodes are fixed by (seed, k)
        seed = np.random.SeedSequence(cfg.seed, spawn_key=(prog.batches,))
        ro = collector.collect(
            learner.policy,
            seed,
            generator,
            cfg.greedy_sender_episodes(prog.episodes, learner.senders_wait.start),
            cfg.held_message_episodes(prog.episodes, learner.senders_wait.start),
        )
        # update
        stats = learner.update(
            ro, generator, progress=cfg.schedule_progress(prog.episodes), rolling_length=prog.rolling_length
        )
        finite_or_stop(out, learner, prog.episodes + len(ro.length))
        prog.wall_s += time.perf_counter() - t0
        row = prog.add_batch(ro.length, ro.team_return, int(ro.length.sum()) * n, sent_greedy=ro.sent_greedy.numpy())
        return {**row, "charts/success": float(ro.success.mean()), **stats}

    def postfix(row: dict[str, Any]) -> dict[str, str]:
        return {"len": f"{row['charts/episode_length_rolling']:.1f}", "ret": f"{np.mean(prog.recent_return):.2f}"}

    with critic_beside_policy(learner, torch.get_num_threads()):
        return train_batches(
            cfg,
            prog,
            logger,
            play_and_learn,
            lambda rank: save_learner(out, cfg, learner, generator, prog, rank=rank),
            postfix,
            progress,
            held_out(cfg, learner.policy),
        )
