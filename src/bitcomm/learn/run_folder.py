"""The run folder both trainers write, and what a run keeps between updates:

    <out>/config.json          TrainConfig + seed, and what ran it (`bitcomm.provenance`): library versions, git
                               commit and whether the source was dirty, command line; and each
                               start or resume with its machine (`write_config`)
    <out>/metrics.csv          one row per batch (flat namespaced keys), the source of every plot
    <out>/tb/                  the same rows for TensorBoard
    <out>/learning_curve.png   mean episode length against episodes, from metrics.csv (and .svg)
    <out>/checkpoints/         see bitcomm.checkpoint
    <out>/.lock                held by the one process writing the folder (bitcomm.run_lock)

A run starts by removing what a killed run left (`prepare`, `bitcomm.checkpoint.clean`), checks its
weights after every update (`finite_or_stop`) and stops, keeping its last good checkpoint as `latest`,
the moment one is NaN or infinite.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import errno
import functools
import json
import math
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from os import PathLike
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
import torch

from bitcomm import provenance
from bitcomm.checkpoint import (
    CHECKPOINTS,
    LATEST,
    clean,
    complete,
    is_run_folder,
    latest_name,
    load_state,
    load_weights,
    read_config,
    refuse_nonfinite,
    resolve,
    save_checkpoint,
)
from bitcomm.config import TaskConfig
from bitcomm.errors import ConfigError, bad_value, one_line, os_error_line
from bitcomm.files import naming, write_atomic, write_text_atomic
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.held_out import HELD_OUT_COLUMN, HeldOut, held_out_seed
from bitcomm.learn.resume_rules import RESUME_MAY_CHANGE, changed_on_resume
from bitcomm.plotting import save_figure
from bitcomm.run_lock import run_lock
from bitcomm.stop_signals import REPEAT_S, Stopped, held

ConfigT = TypeVar("ConfigT")

ROLLING = 1000
"""Episodes in the rolling mean of the progress bar, the log and the plot."""
SAMPLED_ROLLING = "charts/episode_length_sampled_rolling"
"""metrics.csv's column of the rolling length over the episodes whose messages were sampled (`Progress.add_batch`)."""
LEARNING_COLUMNS = ("batch", "episodes", "agent_steps")
"""Columns besides the learner's and the charts; `wall_s` is the only one that is not reproducible."""


# ---------------------------------------------------------------------------------------------- record
def oracle_level(cfg: TrainConfig, episodes: int = 2000) -> float | None:
    """The oracle's mean episode length on the task (None where the oracle cannot play it)."""
    return _oracle_level(cfg.task, cfg.seed, episodes)


def training_oracle_level(cfg: TrainConfig, episodes: int = 2000) -> float | None:
    """The oracle's mean over episodes cut where training cuts its own (`train_max_steps`): the level a rolling
    training length can be compared with. On grids whose oracle needs more steps than training plays (from about
    24x24 with 32-step episodes) it is below `oracle_level`: 25.35 against 27.39 steps on 32x32 (K = 10)."""
    return _oracle_level(cfg.training_task, cfg.seed, episodes)


@functools.lru_cache(maxsize=16)
def _oracle_level(task: TaskConfig, seed: int, episodes: int) -> float | None:
    """`oracle_level`, measured once per task and seed in a process: a run's config.json and the schedules that wait
    for the protocol (`bitcomm.learn.level_watch`) ask for the same figure."""
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.reference import OraclePolicy

    try:
        return evaluate(OraclePolicy(task), task, episodes, seed=seed).mean_episode_length
    except ConfigError:
        return None


def oracle_record(cfg: TrainConfig) -> dict[str, Any]:
    """What a fresh grid run measures once for its config.json: the oracle's level on its task, and the seed of
    its held-out episode set where it evaluates one (`TrainConfig.held_out_every`)."""
    record: dict[str, Any] = {"oracle_mean_episode_length": oracle_level(cfg)}
    if cfg.held_out_every:
        record["held_out_seed"] = held_out_seed(cfg.seed)
    return record


class RunConfig(Protocol):
    """What the run folder reads of a config: the grid's `TrainConfig` or a wrapped env's `EnvTrainConfig`."""

    @property
    def seed(self) -> int: ...
    @property
    def keep_checkpoints(self) -> int: ...
    @property
    def episodes(self) -> int: ...
    @property
    def num_envs(self) -> int: ...
    @property
    def checkpoint_seconds(self) -> float: ...
    def to_dict(self) -> dict[str, Any]: ...


RunConfigT = TypeVar("RunConfigT", bound=RunConfig)


UNRECORDED = "unrecorded"
"""`machine_label` of a start whose machine was not kept (runs made before `starts` were)."""


def machine_label(record: dict[str, Any] | None) -> str:
    """One machine record as a phrase ("AMD EPYC, 2 cores"), `UNRECORDED` for runs made before it was kept."""
    if not record:
        return UNRECORDED
    return f"{record.get('cpu', 'unknown')}, {record.get('cores', '?')} cores"


START_OPTIONS = "options"
"""The key of a start (config.json's `starts`) holding the options a resume may change (`RESUME_MAY_CHANGE`) as that
start had them: the top-level config is the last start's, and a run resumed to a larger budget annealed its first
part over the budget it had then (from Python, whose command line does not show it, nothing else says so)."""
CARRIED = ("oracle_mean_episode_length", "held_out_seed")
"""config.json keys a resumed run keeps from its first start (measured once, not again at every resume)."""


def write_config(
    cfg: RunConfig, out: Path, saved: dict[str, Any] | None, measure: Callable[[Any], dict[str, Any]] | None = None
) -> None:
    """config.json: the config, seed, versions, git commit and command of this start, `measure(cfg)`'s figures
    (a fresh run's) or those a resumed run keeps (`CARRIED`), and `starts`: one entry per start or resume
    (episodes played before it, time, commit, versions, threads, machine, command, and the options a resume may
    change as it had them: `START_OPTIONS`), so a run resumed on another machine or commit, or to a larger budget,
    says which part of it ran where and how."""
    given = cfg.to_dict()
    start = {
        "episodes": int(saved["episodes"]) if saved is not None else 0,
        **provenance.record(),
        START_OPTIONS: {k: given[k] for k in sorted(RESUME_MAY_CHANGE) if k in given},
    }
    starts: list[dict[str, Any]] = []
    if saved is None:
        extra = measure(cfg) if measure is not None else {}
    else:
        previous = read_config_json(out)
        extra = {k: previous[k] for k in CARRIED if k in previous}
        # a run begun before starts were kept: its first start as config.json recorded it, machine unknown
        first = {"episodes": 0, **{k: previous.get(k) for k in ("git_commit", "versions", "command")}}
        starts = recorded_starts(previous, out) or [first]
    record = {
        **cfg.to_dict(),
        "seed": cfg.seed,
        "versions": start["versions"],
        "git_commit": start["git_commit"],
        "git_dirty": start["git_dirty"],
        "command": start["command"],
        **extra,
        "starts": [*starts, start],
    }
    write_text_atomic(out / "config.json", json.dumps(record, indent=2) + "\n")


def recorded_starts(record: dict[str, Any], out: Path) -> list[dict[str, Any]]:
    """The `starts` of the run in `out` from its config.json `record` ([] for a run made before they were kept);
    one line if they are not a list of objects (a hand-edited file), before a resume writes anything."""
    starts = record.get("starts", [])
    if not isinstance(starts, list) or not all(isinstance(s, dict) for s in starts):
        raise ConfigError(f"invalid config={str(out / 'config.json')!r}: its 'starts' is not a list of objects")
    return starts


def run_machines(out: Path) -> list[str]:
    """The machines (`machine_label`) that trained the run in `out`, in the order of its starts ("unrecorded"
    for a run made before they were kept, or a folder without config.json)."""
    starts = (recorded_starts(read_config_json(out), out) if (out / "config.json").is_file() else []) or [{}]
    return list(dict.fromkeys(machine_label(s.get("machine")) for s in starts))


def read_json_object(path: Path, what: str = "file") -> dict[str, Any]:
    """A JSON object from a file of a run folder, or one line naming the file (as `what`) when it is
    missing, unreadable or not a JSON object."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ConfigError(f"invalid {what}={str(path)!r}: unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(record, dict):
        raise ConfigError(f"invalid {what}={str(path)!r}: not a JSON object")
    return record


def read_config_json(out: Path) -> dict[str, Any]:
    """The run's config.json, or one line naming it."""
    return read_json_object(out / "config.json", "config")


def check_config_json(out: Path) -> None:
    """One line unless the run's config.json can take this start's record (a resume appends to its `starts`); a
    folder holding `checkpoints/` alone (copied back from another machine, say) is told what else to bring."""
    path = out / "config.json"
    if not path.exists() and not path.is_symlink():
        raise ConfigError(
            f"invalid config={str(path)!r}: missing; a resume continues the run's record of where and how it ran, so "
            "copy the whole run folder (checkpoints/ alone is enough for eval, render and export)"
        )
    recorded_starts(read_config_json(out), out)


def read_metrics(path: Path, upto_batch: int) -> list[dict[str, str]]:
    """The rows of metrics.csv up to a batch (a torn last row, from a kill, is dropped); one line if corrupt."""
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        if rows and None in rows[-1].values():
            rows.pop()
        kept = [r for r in rows if int(r["batch"]) <= upto_batch]
        for r in kept:
            int(r["episodes"])  # the step from which a resume's TensorBoard writer purges (`Logger`)
        return kept
    except (OSError, ValueError, KeyError, TypeError, csv.Error) as err:
        raise ConfigError(
            f"invalid metrics={str(path)!r}: unreadable on resume ({type(err).__name__}: {err}); "
            "repair or remove it to resume"
        ) from None


TB_EVENTS = "events.out.tfevents.*"
"""The files TensorBoard's writer adds to `<out>/tb`, one per start or resume."""
EVENTS_THREAD = "_AsyncWriterThread"
"""The class of the thread on which TensorBoard's writer writes them (`tensorboard.summary.writer`)."""


class Logger:
    """One row per batch, to metrics.csv and TensorBoard alike (x axis: episodes).

    TensorBoard shows what metrics.csv holds. A resume drops the rows logged past its checkpoint (a `kill -9`
    leaves up to `checkpoint_seconds` of them) from both: from metrics.csv by rewriting it, from TensorBoard by
    the `purge_step` of its writer, which hides every earlier event at or past the first step it will log, so
    no step shows twice or goes backwards. Both are flushed with each row, so that what a checkpoint's resume
    keeps is on disk however the run ends (TensorBoard's writer thread would hold the last rows for up to two
    minutes). A fresh run removes the event files of the run it replaces, as it does metrics.csv."""

    def __init__(self, out: Path, resume_batches: int | None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.path = out / "metrics.csv"
        self.columns: list[str] | None = None
        purge: int | None = None
        if resume_batches is not None:
            rows = read_metrics(self.path, resume_batches) if self.path.is_file() else []
            if rows:
                self.columns = list(rows[0])
            if self.path.is_file():  # drop rows past the checkpoint
                self._rewrite(rows)
            purge = int(rows[-1]["episodes"]) + 1 if rows else 0
        else:
            self.path.unlink(missing_ok=True)
            for events in (out / "tb").glob(TB_EVENTS):
                events.unlink()
        self.file = self.path.open("a", newline="")
        self.events = out / "tb"
        self.events_error: OSError | None = None
        self.hook = threading.excepthook
        threading.excepthook = self._thread_failed
        try:
            with naming(self.events):
                self.tb = SummaryWriter(str(self.events), purge_step=purge)
        except BaseException:
            threading.excepthook = self.hook
            self.file.close()
            raise

    def _thread_failed(self, args: Any) -> None:
        """TensorBoard writes its events on a thread of its own, whose failure to write (a full disk) would print
        that thread's traceback; its writer raises the error again in the run's thread at the next event, and
        `close` at the end, where it ends the run in one line (`stops_in_one_line`)."""
        if type(args.thread).__name__ == EVENTS_THREAD and isinstance(args.exc_value, OSError):
            self.events_error = args.exc_value
            return
        self.hook(args)

    def log(self, row: dict[str, float]) -> None:
        if self.columns is None:
            self.columns = list(row)
            csv.DictWriter(self.file, self.columns).writeheader()
        elif not row.keys() <= set(self.columns):  # a run resumed by another trainer logs more: widen the file
            self.columns += [k for k in row if k not in self.columns]
            self.file.close()
            with self.path.open(newline="") as f:
                rows = list(csv.DictReader(f))
            self._rewrite(rows)
            self.file = self.path.open("a", newline="")
        with naming(self.path):
            csv.DictWriter(self.file, self.columns, extrasaction="ignore").writerow(row)
            self.file.flush()
        step = int(row["episodes"])
        with naming(self.events):
            for key, value in row.items():
                if "/" in key:
                    self.tb.add_scalar(key, value, step)
            self.tb.flush()  # on disk as the row is: a `kill -9` after the next checkpoint must not take them

    def _rewrite(self, rows: list[dict[str, str]]) -> None:
        """metrics.csv as `rows` under `self.columns`, replaced whole: a kill or a full disk midway leaves the rows
        it had, never a file cut short (which a resume would refuse)."""

        def write(tmp: Path) -> None:
            with tmp.open("w", newline="") as f:
                if self.columns:
                    w = csv.DictWriter(f, self.columns)
                    w.writeheader()
                    w.writerows(rows)

        write_atomic(self.path, write)

    def close(self) -> None:
        """Both files, the events too where metrics.csv cannot be flushed (a full disk): its writer's thread
        must not outlive the run; then the error that thread met, if any."""
        try:
            with naming(self.path):
                self.file.close()
        finally:
            self.tb.close()
            if threading.excepthook == self._thread_failed:
                threading.excepthook = self.hook
        if self.events_error is not None:
            with naming(self.events):
                raise self.events_error


def plot_learning_curve(out: Path, metric: str = "episode_length") -> Path:
    """learning_curve.png and .svg from metrics.csv (and the oracle's level from config.json); returns the PNG.

    `metric`: the `charts/<metric>` column and its `_rolling` mean (a run on a wrapped env plots `team_return`)."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    with (out / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    config = json.loads((out / "config.json").read_text())
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    if rows:
        x = np.array([float(r["episodes"]) for r in rows])
        batch = [float(r[f"charts/{metric}"]) for r in rows]
        rolling = [float(r[f"charts/{metric}_rolling"]) for r in rows]
        ax.plot(x, batch, color="C0", alpha=0.25, lw=0.8, label="batch mean")
        ax.plot(x, rolling, color="C0", label=f"last {ROLLING} episodes")
        sampled = [
            (xi, float(r[SAMPLED_ROLLING]), ri)
            for xi, r, ri in zip(x, rows, rolling, strict=True)
            if r.get(SAMPLED_ROLLING)
        ]
        if metric == "episode_length" and any(v != ri for _, v, ri in sampled):  # apart once greedy senders play
            xs, vs, _ = zip(*sampled, strict=True)
            ax.plot(xs, vs, color="C2", lw=1, label=f"last {ROLLING} episodes of sampled messages")
        held = [(float(r["episodes"]), float(r[HELD_OUT_COLUMN])) for r in rows if r.get(HELD_OUT_COLUMN)]
        if held and metric == "episode_length":
            play = "greedy" if config.get("held_out_greedy", True) else "sampled"
            ax.plot(*zip(*held, strict=True), "o-", color="C1", ms=3, lw=1, label=f"held-out episodes ({play})")
    if config.get("oracle_mean_episode_length") is not None:
        ax.axhline(config["oracle_mean_episode_length"], color="k", ls="--", lw=1, label="oracle")
    ax.set_xlabel("episodes")
    if "task" in config:
        cut, limit = config.get("train_max_steps") or 0, config["task"]["env"]["max_steps"]
        ax.set_ylabel("mean episode length" + (f" (training episodes cut at {cut})" if 0 < cut < limit else ""))
        messages = config.get("model", {}).get("messages")
        ax.set_title(f"{config.get('estimator')} + {messages} ({config.get('recipe')}), seed {config.get('seed')}")
    else:
        ax.set_ylabel(f"mean {metric.replace('_', ' ')}")
        ax.set_title(
            f"{config.get('env')}: {config.get('estimator')} + {config.get('messages')}, seed {config.get('seed')}"
        )
    ax.legend(loc="upper right")
    fig.tight_layout()
    return save_figure(fig, out / "learning_curve.png")[0]


# ---------------------------------------------------------------------------------------------- state
class Progress:
    """Counters that a checkpoint carries."""

    def __init__(self) -> None:
        self.episodes = self.batches = self.agent_steps = 0
        self.wall_s = 0.0
        self.recent: deque[int] = deque(maxlen=ROLLING)
        self.recent_return: deque[float] = deque(maxlen=ROLLING)
        self.recent_sampled: deque[int] = deque(maxlen=ROLLING)
        """Lengths of the last episodes whose messages were sampled (not `TrainConfig.greedy_senders`' episodes)."""

    def add_batch(
        self,
        length: np.ndarray,
        team_return: np.ndarray,
        agent_steps: int,
        batches: int = 1,
        sent_greedy: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Count a consumed batch of whole episodes; returns the figures every trainer logs first for it
        (`wall_s` as the caller has set it), in metrics.csv's column order. With `sent_greedy` (the grid's
        trainers), also the rolling length of the episodes whose messages were sampled: from `greedy_senders_from`
        on, the rolling length mixes in the greedy senders' episodes, which are long where the words have not
        formed yet (32x32 at halfway), so it jumps up there whatever the sampled play does."""
        self.batches += batches
        self.episodes += len(length)
        self.agent_steps += agent_steps
        self.recent.extend(int(x) for x in length)
        self.recent_return.extend(float(x) for x in team_return)
        row = {
            "batch": self.batches,
            "episodes": self.episodes,
            "agent_steps": self.agent_steps,
            "wall_s": round(self.wall_s, 3),
            "charts/episode_length": float(np.mean(length)),
            "charts/episode_length_rolling": self.rolling_length,
            "charts/team_return": float(np.mean(team_return)),
        }
        if sent_greedy is not None:
            self.recent_sampled.extend(int(x) for x in length[~np.asarray(sent_greedy, dtype=bool)])
            if self.recent_sampled:  # none yet where every sender has been greedy from the first batch
                row[SAMPLED_ROLLING] = float(np.mean(self.recent_sampled))
        return row

    @property
    def rolling_length(self) -> float | None:
        """The rolling mean episode length (None before the first batch)."""
        return float(np.mean(self.recent)) if self.recent else None

    def state(self) -> dict[str, Any]:
        return {
            "agent_steps": self.agent_steps,
            "wall_s": self.wall_s,
            "recent_lengths": torch.tensor(list(self.recent), dtype=torch.int64),
            "recent_returns": torch.tensor(list(self.recent_return), dtype=torch.float64),
            "recent_sampled_lengths": torch.tensor(list(self.recent_sampled), dtype=torch.int64),
        }

    def restore(self, state: dict[str, Any]) -> None:
        self.episodes, self.batches = int(state["episodes"]), int(state["batches"])
        self.agent_steps, self.wall_s = int(state["agent_steps"]), float(state["wall_s"])
        self.recent.extend(int(x) for x in state["recent_lengths"].tolist())
        self.recent_return.extend(float(x) for x in state["recent_returns"].tolist())
        # a checkpoint from before the column: its lengths are the best guess (equal unless greedy senders played)
        self.recent_sampled.extend(
            int(x) for x in state.get("recent_sampled_lengths", state["recent_lengths"]).tolist()
        )


WATCHES = ("move_decay", "senders_wait")
"""The grid learner's `bitcomm.learn.level_watch` watches: a checkpoint holds where each started."""


def learner_state(learner: Any, generator: torch.Generator | None = None) -> dict[str, Any]:
    """What a checkpoint holds besides the weights and the counters so that a resumed run continues as if
    never stopped: both optimizers' moments and the random streams (`generator`: the trainer's own, if any)."""
    state: dict[str, Any] = {
        "opt_policy": learner.opt_policy.state_dict(),
        "opt_critic": learner.opt_critic.state_dict(),
    }
    if generator is not None:
        state["generator"] = generator.get_state()
    state["torch_rng"] = torch.get_rng_state()
    for name in WATCHES:  # the grid learner's schedules that wait for the protocol, where they started
        watch = getattr(learner, name, None)
        if watch is not None and watch.waits and watch.start is not None:
            state[f"{name}_start"] = watch.start
    return state


def checkpoint_weights(learner: Any) -> dict[str, dict[str, torch.Tensor]]:
    weights = {"policy": learner.policy.state_dict(), "critic": learner.critic.state_dict()}
    if learner.codebook is not None:
        weights["codebook"] = learner.codebook.state_dict()
    return weights


# how an optimizer runs, not what it has learned: a checkpoint's values (older ones saved `fused` as None)
# must not replace the ones this code builds its optimizer with
_EXECUTION_FLAGS = ("fused", "foreach", "capturable", "differentiable")


def load_optimizer(opt: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Moments, step counts and learning rates of a saved optimizer, run the way `opt` was built."""
    flags = [{k: g[k] for k in _EXECUTION_FLAGS if k in g} for g in opt.param_groups]
    opt.load_state_dict(state)
    for group, kept in zip(opt.param_groups, flags, strict=True):
        group.update(kept)


def restore_learner(learner: Any, saved: dict[str, Any]) -> None:
    """Weights, code book and optimizer moments of a checkpoint's state into a fresh Learner (built from the
    checkpoint's config); one line naming the checkpoint where they do not fit it, never a learner resumed with
    some of its networks freshly initialised."""

    def bad(why: str) -> ConfigError:
        return ConfigError(f"invalid checkpoint={saved.get('info', {}).get('path')!r}: {why}")

    needed, held = sorted(checkpoint_weights(learner)), sorted(saved["weights"])
    if held != needed:
        raise bad(f"it holds the weights of {held}, its config needs {needed}")
    try:
        for name, sd in saved["weights"].items():
            getattr(learner, name).load_state_dict(sd)
        load_optimizer(learner.opt_policy, saved["opt_policy"])
        load_optimizer(learner.opt_critic, saved["opt_critic"])
    except ConfigError:
        raise
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise bad(f"it does not fit its config ({one_line(err)})") from None
    for name in WATCHES:
        if f"{name}_start" in saved:
            getattr(learner, name).start = float(saved[f"{name}_start"])


def resume_config(out: Path, from_dict: Callable[[dict[str, Any]], ConfigT], episodes: int | None = None) -> ConfigT:
    """The config the run in `out` was started with (`TrainConfig.from_dict`, or a wrapped env's
    `EnvTrainConfig.from_dict`), with a new budget if one is given. It reads the checkpoint's metadata alone:
    `prepare` reads and checks the tensors when the run resumes."""
    check_start(out, resume=True)
    check_config_json(out)  # which `prepare` reads again: a damaged one stops the run before a line is printed
    d = read_config(out)
    if episodes is not None:
        d["episodes"] = episodes
    return config_of(resolve(out), d, from_dict)


def config_of(source: Path | str, d: dict[str, Any], from_dict: Callable[[dict[str, Any]], ConfigT]) -> ConfigT:
    """`from_dict(d)` of a config read from `source` (a checkpoint, a config.json), or one line naming it where the
    config does not fit this bitcomm's: a key missing or unknown, a value of the wrong type (a hand-edited file, or
    one another version wrote)."""
    try:
        return from_dict(d)
    except ConfigError:  # a value out of range names itself
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        what = "config" if Path(source).name == "config.json" else "checkpoint"
        raise ConfigError(
            f"invalid {what}={str(source)!r}: its config does not fit this bitcomm ({one_line(err)})"
        ) from None


def has_checkpoint(out: Path) -> bool:
    return (out / CHECKPOINTS / LATEST).is_file()


RUN_FILES = ("config.json", "metrics.csv", "learning_curve.png", "learning_curve.svg", "tb")
"""The files (and TensorBoard's folder) a run writes at its folder's top, which a fresh run overwrites."""


def run_folder(out: object) -> Path:
    """`out` of `train(cfg, out)` as a Path, or one line: an empty one would be the current folder, as `--out ""` is
    refused, and one that is no path (None) was pathlib's TypeError, naming no argument."""
    if not isinstance(out, (str, PathLike)) or not str(out):
        raise bad_value("out", out, "must be the run's folder, a non-empty str or a Path")
    return Path(out)


def check_start(out: Path, resume: bool) -> None:
    """One line, before anything is written, for a start `out` cannot take: a resume without a checkpoint, a
    fresh run where a run is, or a fresh run that would overwrite files of `RUN_FILES` that are not a run's. A run
    stopped before its first checkpoint is started again from scratch."""
    is_run = is_run_folder(out)  # read once: the lock, the advice and the overwrite check all ask it
    if is_run:  # a run being written: the line naming its pid, before `run folder:` is printed
        with run_lock(out):
            pass
    if resume:
        if not has_checkpoint(out):
            kept = complete(out / CHECKPOINTS) if (out / CHECKPOINTS).is_dir() else []
            if kept:  # latest.json lost (deleted, not synced): a fresh start would remove these, never advise it
                episodes, last = kept[-1]
                why = (
                    f"its {CHECKPOINTS}/{LATEST} is missing, though it holds checkpoints up to {last.name}; to "
                    f"resume from that one, {pointed_at(episodes, last)}"
                )
            elif is_run:
                why = (
                    "this run stopped before its first checkpoint (one is written every --checkpoint-seconds), so "
                    "there is nothing to resume; train it again without --resume"
                )
            else:
                why = f"no checkpoint to resume from ({CHECKPOINTS}/{LATEST} missing)"
            raise ConfigError(f"invalid out={str(out)!r}: {why}")
        return
    if has_checkpoint(out):
        raise ConfigError(f"invalid out={str(out)!r}: it already holds a run (use --resume, or another --out)")
    present = [name for name in RUN_FILES if (out / name).exists()]
    if present and not is_run:
        raise ConfigError(
            f"invalid out={str(out)!r}: it holds {present[0]}, which is not a bitcomm run's and a new run would "
            "overwrite it; give another --out"
        )


def prepare(cfg: RunConfigT, out: Path, resume: bool) -> tuple[RunConfigT, dict[str, Any] | None]:
    """Check the folder (its lock held) and clear what a killed run left; return the config the run goes on under
    (`cfg`, its budget kept by `kept_budget` where a resume asks for less than was played) and, on resume, the
    checkpoint's state (with its weights), else None."""
    check_start(out, resume)
    clean(out)
    if not resume:
        return cfg, None
    with older_checkpoint_advised(out):  # a damaged file, not a config this resume may not change
        weights, info = load_weights(out)
        state = load_state(resolve(out))
        for key in ("episodes", "batches", "agent_steps", "wall_s", "recent_lengths", "recent_returns"):
            if key not in state:
                raise ConfigError(f"invalid checkpoint={info['path']!r}: its resume state lacks {key!r}")
    check_resumed_as_started(cfg, out, info["config"])
    # refuse a damaged config.json or metrics.csv before anything is written
    check_config_json(out)
    if (out / "metrics.csv").exists():  # a folder of that name too, before the log would fail on it
        read_metrics(out / "metrics.csv", int(state["batches"]))
    played = int(state["episodes"])
    if played >= cfg.episodes:  # `make train` run again: say why nothing trains
        recorded = int(info["config"]["episodes"])
        budget = kept_budget(cfg.episodes, played, recorded)
        note = budget_note(cfg.episodes, budget, recorded)
        print(f"{out}: already played {played:,} episodes of --episodes {cfg.episodes:,}; nothing to train{note}")
        cfg = dataclasses.replace(cfg, episodes=budget)  # type: ignore[type-var]  # both configs are dataclasses
    return cfg, {**state, "weights": weights, "info": info}


def kept_budget(asked: int, played: int, recorded: int) -> int:
    """The budget a run records when a resume asks for `asked` episodes, `played` of them already played under the
    `recorded` budget: `asked`, unless that is below what was played, where nothing trains and the record keeps the
    budget it had, or what was played if that is less (a run stopped short of it): a resume that trained nothing
    wrote the smaller figure into config.json and the checkpoint as the run's budget."""
    return asked if asked >= played else max(asked, min(recorded, played))


def budget_note(asked: int, kept: int, recorded: int) -> str:
    """What a resume that trains nothing says of the budget it records (`kept_budget`) where that is not the one
    asked: a run stopped short of its budget was told its budget "stays" at what it played, which it had not."""
    if kept == asked:
        return ""
    if kept == recorded:
        return f" (its budget stays {kept:,})"
    return f" (its budget is now {kept:,}, the episodes played, not {recorded:,})"


def pointed_at(episodes: int, file: Path) -> str:
    """How to make a run resume from its checkpoint `file` of `episodes` episodes."""
    return f'write {CHECKPOINTS}/{LATEST} as {{"checkpoint": "{file.name}", "episodes": {episodes}}}'


@contextlib.contextmanager
def older_checkpoint_advised(out: Path) -> Iterator[None]:
    """A latest checkpoint refused on resume (damaged, say) is one line that also says how to resume from the newest
    older one the run keeps: one bad file need not cost the run its earlier checkpoints, as a fresh start would."""
    try:
        yield
    except ConfigError as err:
        latest = resolve(out).name
        older = [(e, f) for e, f in complete(out / CHECKPOINTS) if f.name < latest]  # zero-padded: by episodes
        if not older:
            raise
        raise ConfigError(f"{err}; to resume from the older {older[-1][1].name}, {pointed_at(*older[-1])}") from None


def check_resumed_as_started(cfg: RunConfig, out: Path, recorded: dict[str, Any]) -> None:
    """One line where `cfg` would change what the run in `out` learns (its checkpoint's `recorded` config): a resume
    continues a run as it started, as `bitcomm train --resume` does, where `train(cfg, out, resume=True)` from
    Python went on silently under another seed, learning rate or batch, and recorded it as the whole run's."""
    changed = changed_on_resume(recorded, cfg.to_dict())
    if changed:
        name, value, was = changed[0]
        raise bad_value(
            name,
            value,
            f"the run in {str(out)!r} was trained with {name}={was!r}, and a resume continues it as it started (only "
            "the budget, where it runs and how often it saves may change)",
        )


FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""A full disk, a quota used up, a file past the size limit a process was given (`ulimit -f`)."""


RESUMES = "--resume (or the same study again) goes on"
"""Where a stopped run goes on: `train --resume`, or, for a study's run (`compare`, `scaling`), the study again."""


@contextlib.contextmanager
def stops_in_one_line(out: Path) -> Iterator[None]:
    """A file of the run the system will not write (a full disk, a quota, a folder made read-only meanwhile) stops
    the run with an `OSError` that says so and what `--resume` goes on from: every file is replaced whole
    (`bitcomm.files`), so the latest checkpoint is intact, and the rows and events logged past it are dropped on
    resume (`Logger`)."""
    try:
        yield
    except OSError as err:
        latest = latest_name(out)
        once = "there is room" if err.errno in FULL else "the file can be written"
        resumes = f"{RESUMES} from it once {once}"
        then = f"; its latest checkpoint, {latest}, is whole: {resumes}" if latest else " before its first checkpoint"
        raise OSError(err.errno, f"{os_error_line(err)}; the run stopped{then}") from err


def save_learner(
    out: Path,
    cfg: RunConfig,
    learner: Any,
    generator: torch.Generator,
    prog: Progress,
    metric: str = "episode_length",
    extra: dict[str, Any] | None = None,
    rank: float | None = None,
) -> Path:
    """A checkpoint of a trainer with one learner: its weights, optimizers and random streams, the counters,
    and what else the trainer needs to resume (`extra`); `rank` as `save_run_checkpoint`'s."""
    state = {**prog.state(), **learner_state(learner, generator), **(extra or {})}
    return save_run_checkpoint(out, cfg, checkpoint_weights(learner), prog, state, metric, rank)


def stopped(signum: int, episodes: int, path: Path) -> Stopped:
    """`Stopped` for a run saved at `path` after `episodes`, once its line is printed: what a trainer raises when
    `stop_after_batch` asked it to stop."""
    name = signal.Signals(signum).name
    print(f"stopped after {episodes} episodes on {name}, saved as {path}; {RESUMES}", file=sys.stderr)
    return Stopped(signum, path, episodes)


def saved_or_stopped(stop_asked: Callable[[], int | None], episodes: int, save: Callable[[], Path], bar: Any) -> Path:
    """The end of a trainer's loop: its last checkpoint saved (`save()`), then its path, or, where `stop_after_batch`
    asked for a stop (`stop_asked()`, or a stop signal that came while it saved), the progress bar closed and
    `stopped` raised. A stop signal repeated while it saves waits for the save (`held`), then is dropped: the run is
    stopping, saved, as it would have."""
    with held() as waiting:
        path = save()
        signum = stop_asked() or next(iter(waiting), None)
        if signum is not None:
            bar.close()
            raise stopped(signum, episodes, path)
    return path


def _stoppable_signals() -> list[signal.Signals]:
    """The signals a training loop may take over: SIGINT where Python's own handler has it (not where it is
    ignored, as in a background job, or another handler took it), and SIGTERM (what `kill PID` and a cluster
    scheduler's time limit send) where it would kill the process, in a process started as a program (a
    study's worker keeps SIGTERM's default: its parent asks it to stop with SIGINT, `studies.compare.stop_runs`,
    and ends it with SIGTERM, at once, when it does not)."""
    import multiprocessing

    if threading.current_thread() is not threading.main_thread():
        return []
    wanted = [signal.SIGINT] if signal.getsignal(signal.SIGINT) is signal.default_int_handler else []
    if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL and multiprocessing.parent_process() is None:
        wanted.append(signal.SIGTERM)
    return wanted


@contextlib.contextmanager
def stop_after_batch() -> Iterator[Callable[[], int | None]]:
    """Ctrl-C or SIGTERM while training asks the loop to stop after the batch it is on, so that the run can
    save it and lose nothing (without this, up to `checkpoint_seconds` of training); the same signal again
    (`REPEAT_S` or more later) stops at once, or, during a save, once it is whole (`save_run_checkpoint`). Yields a
    function that returns the signal asked for, or None."""
    asked: list[int] = []
    taken = {s: signal.getsignal(s) for s in _stoppable_signals()}
    first: dict[int, float] = {}

    def ask(signum: int, frame: object) -> None:
        if signum not in first:
            first[signum] = time.monotonic()
            asked.append(signum)
        elif time.monotonic() - first[signum] >= REPEAT_S:  # the previous handler: KeyboardInterrupt, or death
            signal.signal(signum, taken[signal.Signals(signum)])
            signal.raise_signal(signum)

    for s in taken:
        signal.signal(s, ask)
    try:
        yield lambda: asked[0] if asked else None
    finally:
        for s, previous in taken.items():
            signal.signal(s, previous)


def train_batches(
    cfg: RunConfig,
    prog: Progress,
    logger: Logger,
    play_and_learn: Callable[[], dict[str, Any]],
    save: Callable[[float | None], Path],
    postfix: Callable[[dict[str, Any]], dict[str, str]],
    progress: bool = True,
    held_out: HeldOut | None = None,
) -> Path:
    """The synchronous trainers' loop (the grid's and a wrapped env's): `play_and_learn()` plays and learns
    one batch, counts it in `prog` and returns its log row; a checkpoint every `checkpoint_seconds` and
    one at the end (returned); the progress bar shows `postfix(row)`. Closes the log however it ends.
    Ctrl-C or SIGTERM stops it after the current batch with a checkpoint of it (`stop_after_batch`), then raises
    `Stopped`, a KeyboardInterrupt, as an interrupt would.

    With `held_out`, each batch that crosses an evaluation point is followed by the evaluation (its seconds
    count in `wall_s`, its figure in the batch's log row) and a checkpoint ranked by it (`save(rank)`); the
    checkpoints between are written unranked (`save(inf)`), so retention keeps the one that played the held-out
    episodes best. Without, `save(None)` ranks by the rolling mean."""
    from tqdm import tqdm

    planned = -(-cfg.episodes // cfg.num_envs) * cfg.num_envs  # whole batches: the episodes that will be played
    bar = tqdm(total=planned, initial=prog.episodes, disable=not progress, unit="ep", dynamic_ncols=True)
    last_save = time.monotonic()
    unranked = math.inf if held_out is not None else None
    try:
        with stop_after_batch() as stop_asked:
            rank: float | None = None
            while prog.episodes < cfg.episodes:
                before = prog.episodes
                row = play_and_learn()
                score = None
                if held_out is not None and held_out.due(before, prog.episodes, cfg.episodes):
                    t0 = time.perf_counter()
                    score = held_out.play()
                    prog.wall_s += time.perf_counter() - t0
                    row = {**row, "wall_s": round(prog.wall_s, 3), HELD_OUT_COLUMN: score}
                rank = unranked if score is None else score
                logger.log(row)
                bar.update(prog.episodes - before)
                bar.set_postfix(**postfix(row))
                if stop_asked() is not None or prog.episodes >= cfg.episodes:
                    break
                if score is not None or time.monotonic() - last_save >= cfg.checkpoint_seconds:
                    save(rank)
                    last_save = time.monotonic()
            else:
                rank = None if held_out is None else held_out.play()  # resumed at its budget: nothing to play
            # a stop asked while the last checkpoint was saved (its plot takes a second) stops here, not after the
            # final evaluation: it was dropped, and the command went on to evaluate and exit 0
            return saved_or_stopped(stop_asked, prog.episodes, lambda: save(rank), bar)
    finally:
        bar.close()
        logger.close()


def finite_or_stop(out: Path, learner: Any, episodes: int) -> None:
    """After an update: stop with one line if a weight became NaN or inf (the next rollout could not sample)."""
    refuse_nonfinite(out, episodes, **checkpoint_weights(learner))


def save_run_checkpoint(
    out: Path,
    cfg: RunConfig,
    weights: dict[str, dict[str, torch.Tensor]],
    prog: Progress,
    state: dict[str, Any],
    metric: str = "episode_length",
    rank: float | None = None,
) -> Path:
    """One checkpoint of the run (sync, a3c or a wrapped env), then the plot of `metric` (a finished run whose
    plot the system refuses warns in one line instead of failing: its files are saved). Retention keeps the
    best by `rank` where one is given (a held-out evaluation's mean episode length, inf between evaluations),
    else by the rolling mean of `metric`: the shortest episodes, or (`team_return`) the highest return."""
    rolling = float(np.mean(prog.recent)) if prog.recent else None
    ranked = -float(np.mean(prog.recent_return)) if metric == "team_return" and prog.recent_return else rolling
    if rank is not None:
        ranked = rank
    with held():  # a stop signal meanwhile waits: the plot is drawn from the rows the checkpoint holds
        path = save_checkpoint(
            out,
            cfg.to_dict(),
            weights,
            prog.episodes,
            prog.batches,
            state,
            rolling_length=rolling,
            keep=cfg.keep_checkpoints,
            rank=ranked,
        )
        try:
            plot_learning_curve(out, metric)
        except OSError as err:
            if prog.episodes < cfg.episodes:  # mid-run: the disk that refused it would refuse the next checkpoint
                raise
            # finished and saved: the curve is only drawn from metrics.csv, so the run has not failed
            resume = f"`bitcomm train --resume --out {out}` draws it"
            print(f"warning: {os_error_line(err)}; the run is finished and saved; {resume}", file=sys.stderr)
    return path
