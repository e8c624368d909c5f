"""The four-technique study: the paper's techniques and a learned no-communication baseline, each trained
over several seeds at one budget, measured on one episode set and set against the oracle.

    <out>/runs/<configuration>/seed<k>/  a `bitcomm train` run folder per run, plus its evaluation.json
    <out>/curves.csv                     every run's learning curve, read from its metrics.csv
    <out>/curves.png, curves.svg         rolling mean episode length against episodes: mean and 95%
                                         interval over seeds per configuration, the oracle as a line
    <out>/table.md, summary.json         per configuration: final evaluation (sampled, greedy, and sampled
                                         with the channel cut), the episodes and seconds until the rolling
                                         mean falls below 2x and 1.15x the oracle, wall time; each a mean
                                         and 95% interval over seeds; then each seed's figures, and the
                                         rolling mean along the budget

A configuration is a technique with one value of each varied option (`vary={"flip_prob": (0, 0.05)}`),
so a noise study is the same study. The learned baseline `no-comm` is `improved-bitwise` trained and
measured with every message dropped (drop probability 1): what acting alone can do.

Runs go to a pool of spawned processes with one torch thread each. A run whose checkpoint has reached
the budget is skipped and a partial one resumed, so an interrupted study picks up where it stopped;
the files at the top of `<out>` are derived from the run folders alone and rewritten on every call.
The evaluation set has its own seed (`eval_seed`, never a training seed), so no run is measured on
episodes it trained on, and every configuration faces the same episodes. Each run is played three ways
(`PLAYS`); the channel cut (every message dropped at evaluation) is the control that tells communication
from acting alone: a policy that learned to talk loses its skill there, one that did not loses nothing.
An evaluation written before a play was added gains that play alone on the next call.

`report=True` (`bitcomm compare --report`) trains nothing: the tables are written from the runs that have
played their budget (evaluating what their evaluation lacks), so a study still training, or one whose
configurations have finished different numbers of seeds, can be reported at any time.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import itertools
import json
import math
import multiprocessing
import os
import signal
import time
import typing
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from bitcomm.config import MAX_SEED, ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError, bad_value, check_int, plural
from bitcomm.files import write_atomic, write_text_atomic
from bitcomm.learn.options import Option, learning_options
from bitcomm.learn.recipes import DEFAULT_RECIPE
from bitcomm.learn.resume_rules import SAVING, flat
from bitcomm.plotting import log_scale_suits, save_figure
from bitcomm.policies.source import TASK_FLAGS
from bitcomm.stats import mean_interval
from bitcomm.stop_signals import deaf_children, ignore_stop_signals, repeats_count_once, sigterm_interrupts
from bitcomm.studies.tables import task_title

if TYPE_CHECKING:
    from bitcomm.learn.config import TrainConfig
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.policies.evaluation import EvalResult
    from bitcomm.studies.env_compare import EnvCompareConfig

TECHNIQUES: dict[str, tuple[str, str]] = {
    "standard-onehot": ("standard", "onehot"),
    "standard-bitwise": ("standard", "bitwise"),
    "improved-onehot": ("improved", "onehot"),
    "improved-bitwise": ("improved", "bitwise"),
}
"""The paper's four techniques: (estimator, message head)."""
NO_COMM = "no-comm"
"""The learned baseline: `improved-bitwise` with every message dropped."""
CHOICES = (*TECHNIQUES, NO_COMM)
THRESHOLDS = (2.0, 1.15)
"""Levels, as multiples of the oracle's mean episode length, whose first crossing is timed."""
GRID_POINTS = 200
"""Points of the common episode grid the seeds' curves are interpolated onto for the plot."""
CSV_POINTS = 1000
"""At most this many rows of each run's curve go to curves.csv (evenly spaced, always the last)."""
BUDGET_FRACTIONS = (0.125, 0.25, 0.5, 0.75, 1.0)
"""Where along the budget the tables read every run's rolling curve (equal episodes, before the end)."""
EVALUATION = "evaluation.json"
PLAYS = ("sampled", "greedy", "cut")
"""How each run is measured: sampling, the most likely action and message, and sampling with the channel cut
(every message dropped)."""
RESUMABLE = ("episodes", *SAVING, "env_workers")
"""Config fields a finished or partial run may differ in from the study and still count as its run: those of
`RESUME_MAY_CHANGE` that a study's runs can differ in (a study picks the backend and workers of all of them)."""
STUDY_EPISODES = 60_000
"""The default budget of every run: on the default task, improved + bitwise under `reinforced` is below
2x the oracle after 27,000-39,000 episodes and its rolling mean near 1.25x after 60,000 (docs/tuning.md, session 8), so
the techniques separate within it; a run takes about 5 minutes on one core."""


GRID_STUDY_SEEDS = 5
ENV_STUDY_SEEDS = 3
"""Default seeds per configuration: on the grid, and on a wrapped env (`bitcomm.studies.env_compare`), whose runs
are longer."""


def _task_options() -> dict[str, tuple[str, str, Option]]:
    """The task flags with a number value: flag dest -> (config part, field, option)."""
    hints = {"env": typing.get_type_hints(EnvConfig), "channel": typing.get_type_hints(ChannelConfig)}
    return {
        dest: (part, name, Option(dest, hints[part][name], None))
        for dest, (part, name) in TASK_FLAGS.items()
        if hints[part][name] in (int, float)
    }


TASK_OPTIONS = _task_options()


def varied_options() -> dict[str, Option]:
    """Everything `vary` accepts: every learning option and every numeric task option."""
    return {**learning_options(), **{dest: option for dest, (_, _, option) in TASK_OPTIONS.items()}}


def parse_vary(text: str) -> tuple[str, tuple[Any, ...]]:
    """`NAME=V1,V2,...` (dashes allowed in NAME) -> (name, typed values), or one error line."""
    name, sep, values = text.partition("=")
    name = name.strip().replace("-", "_")
    options = varied_options()
    if not sep or name not in options:
        raise bad_value("vary", text, f"expected NAME=V1,V2,... with NAME one of {', '.join(options)}")
    parsed = tuple(options[name].parse(v) for v in values.split(",") if v.strip())
    if not parsed:
        raise bad_value("vary", text, "give at least one value")
    if len(set(parsed)) != len(parsed):
        raise bad_value("vary", text, "values repeat")
    return name, parsed


def parse_techniques(text: str) -> tuple[str, ...]:
    """`improved-bitwise,no-comm` -> a tuple in the order given, or one error line."""
    names = tuple(t.strip() for t in text.split(",") if t.strip())
    if not names or any(t not in CHOICES for t in names) or len(set(names)) != len(names):
        raise bad_value("techniques", text, f"a comma-separated subset of {', '.join(CHOICES)}")
    return names


def _format(value: Any) -> str:
    """A varied value as names, folders and tables show it: 0.05, 0.0003, 1e-05, true (exact, so two values
    never share a folder)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        short = f"{value:g}"
        return short if float(short) == value else repr(value)
    return str(value)


# ---------------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class CompareConfig:
    """One study; `bitcomm compare`'s flags one for one."""

    out: Path = Path("runs/compare")
    techniques: tuple[str, ...] = CHOICES
    recipe: str = DEFAULT_RECIPE
    seeds: int = GRID_STUDY_SEEDS
    """How many seeds of every configuration: first_seed .. first_seed + seeds - 1."""
    first_seed: int = 0
    """The first of them, so that one study can be split across machines, or its later seeds added elsewhere."""
    episodes: int = STUDY_EPISODES
    """The budget of every run."""
    jobs: int = field(default_factory=lambda: os.cpu_count() or 1)
    """Processes at once (an a3c run counts as its workers)."""
    eval_episodes: int = 1000
    eval_seed: int = 1000
    """Seed of the evaluation episode set (and of sampling); may not be a training seed."""
    task: TaskConfig = field(default_factory=TaskConfig)
    learning: dict[str, Any] = field(default_factory=dict)
    """Learning options given explicitly; the others are the recipe's."""
    vary: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    """Option name -> values; configurations are techniques x the product of these."""
    report: bool = False
    """Train nothing: report the runs that have played their budget."""

    def __post_init__(self) -> None:
        check_study_fields(self)
        check_int("episodes", self.episodes, 1)
        unknown = set(self.vary) - set(varied_options())
        if unknown:
            raise bad_value("vary", sorted(unknown)[0], "not a learning or task option")


def check_study_fields(cfg: CompareConfig | EnvCompareConfig) -> None:
    """What every study must hold: known techniques, counts >= 1, an evaluation seed that trains no run."""
    if not cfg.techniques or any(t not in CHOICES for t in cfg.techniques):
        raise bad_value("techniques", cfg.techniques, f"choose from {', '.join(CHOICES)}")
    for name in ("seeds", "jobs", "eval_episodes"):
        check_int(name, getattr(cfg, name), 1)
    check_int("first_seed", cfg.first_seed, 0)
    seeds = study_seeds(cfg)
    if seeds[-1] > MAX_SEED:
        raise bad_value("first-seed", cfg.first_seed, f"its last seed, {seeds[-1]}, must be at most {MAX_SEED}")
    if cfg.eval_seed in seeds:
        raise bad_value("eval-seed", cfg.eval_seed, f"must not be a training seed ({seeds[0]}..{seeds[-1]})")


def study_seeds(cfg: CompareConfig | EnvCompareConfig) -> range:
    """The training seeds of every configuration."""
    return range(cfg.first_seed, cfg.first_seed + cfg.seeds)


class Configuration(NamedTuple):
    """A technique with one value of each varied option; `variant` names the values alone (a plot panel),
    `task_variant` the task options among them (what the oracle's level depends on)."""

    technique: str
    values: tuple[tuple[str, Any], ...] = ()

    @property
    def variant(self) -> str:
        return " ".join(f"{k}={_format(v)}" for k, v in self.values)

    @property
    def task_variant(self) -> str:
        return " ".join(f"{k}={_format(v)}" for k, v in self.values if k in TASK_OPTIONS)

    @property
    def name(self) -> str:
        return f"{self.technique} {self.variant}".strip()

    @property
    def folder(self) -> str:
        return self.name.replace(" ", "_")


Describe = Callable[[Any, str, Any], str]
"""(run, the status it was found in, the study's config) -> the progress line logged when it is finished."""


class Run(NamedTuple):
    """One run of a study: on the grid (`TrainConfig`) or on a wrapped PettingZoo env (`EnvTrainConfig`,
    `bitcomm.studies.env_compare`)."""

    configuration: Configuration
    seed: int
    train: TrainConfig | EnvTrainConfig
    folder: Path


def variant_task(cfg: CompareConfig, values: tuple[tuple[str, Any], ...]) -> TaskConfig:
    """The study's task with the varied task options applied (validated by the configs)."""
    changes: dict[str, dict[str, Any]] = {"env": {}, "channel": {}}
    for name, value in values:
        if name in TASK_OPTIONS:
            part, fname, option = TASK_OPTIONS[name]
            changes[part][fname] = option.kind(value)
    return TaskConfig(
        dataclasses.replace(cfg.task.env, **changes["env"]), dataclasses.replace(cfg.task.channel, **changes["channel"])
    )


def train_config(cfg: CompareConfig, conf: Configuration, seed: int) -> TrainConfig:
    from bitcomm.learn.config import make_train_config

    task = variant_task(cfg, conf.values)
    if conf.technique == NO_COMM:
        task = TaskConfig(task.env, dataclasses.replace(task.channel, drop_prob=1.0))
    estimator, messages = TECHNIQUES.get(conf.technique, TECHNIQUES["improved-bitwise"])
    learning = {**cfg.learning, **{k: v for k, v in conf.values if k not in TASK_OPTIONS}}
    return make_train_config(
        cfg.recipe, task, estimator=estimator, messages=messages, seed=seed, episodes=cfg.episodes, **learning
    )


def plan(cfg: CompareConfig) -> list[Run]:
    """Every run of the study, seed by seed (so a study stopped early has every configuration's first
    seeds); every config is built, so a bad value stops the study before anything is trained."""
    products = itertools.product(*([(name, v) for v in values] for name, values in cfg.vary.items()))
    configurations = [Configuration(t, values) for values in products for t in cfg.techniques]
    return check_budget(
        [
            Run(conf, seed, train_config(cfg, conf, seed), cfg.out / "runs" / conf.folder / f"seed{seed}")
            for seed in study_seeds(cfg)
            for conf in configurations
        ]
    )


def check_budget(runs: list[Run]) -> list[Run]:
    """`runs`, unless a budget is below one batch: a run plays whole batches, so it would play a batch while the
    study's tables read its curve at fractions of a budget it never logged (one line instead)."""
    for run in runs:
        if run.train.episodes < run.train.num_envs:
            raise bad_value(
                "episodes", run.train.episodes,
                f"less than one batch ({run.train.num_envs} episodes, --num-envs), and runs play whole batches; "
                f"use at least {run.train.num_envs}",
            )  # fmt: skip
    return runs


# ---------------------------------------------------------------------------------------------- runs
def _latest(folder: Path) -> dict[str, Any]:
    """The run's checked `latest.json` (it names a checkpoint of its own folder)."""
    from bitcomm.checkpoint import CHECKPOINTS, read_latest

    return read_latest(folder / CHECKPOINTS)


def run_status(run: Run) -> str:
    """`new`, `resume` (a checkpoint short of the budget, which may have changed) or `done` (the budget played);
    an error for a folder holding another run, or one that played past this budget under another."""
    return folder_status(run.folder, run.train)


def folder_status(folder: Path, train: TrainConfig | EnvTrainConfig) -> str:
    """`run_status` of the run `train` in `folder`, for any study that keeps one run per folder."""
    from bitcomm.checkpoint import CHECKPOINTS, LATEST

    latest = folder / CHECKPOINTS / LATEST
    if not latest.is_file():
        return "new"
    recorded, wanted = flat(recorded_config(folder, type(train)).to_dict()), flat(train.to_dict())
    differs = [k for k in wanted if k not in RESUMABLE and recorded.get(k) != wanted[k]]
    if differs:
        raise bad_value("out", str(folder), f"it holds a run with other {', '.join(differs)}; use another --out")
    played, budget = _latest(folder)["episodes"], train.episodes
    if played < budget:
        return "resume"
    if recorded["episodes"] != budget:
        raise bad_value("episodes", budget, f"{folder} has played {played} of a budget of {recorded['episodes']}")
    return "done"


def recorded_config(folder: Path, kind: type[Any]) -> Any:
    """The config (a `kind`: TrainConfig or EnvTrainConfig) in a run's config.json; fields added since it was
    written take their defaults; one line for a run of the other kind (a study of the grid and one on a wrapped env
    in the same --out) or a config.json that is no run's."""
    from bitcomm.checkpoint import is_env_config
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.run_folder import read_json_object

    record = read_json_object(folder / "config.json", "config")
    if is_env_config(record) != (kind is EnvTrainConfig):
        held = f"a run on a wrapped env ({record['env']})" if is_env_config(record) else "a run of the grid task"
        raise bad_value("out", str(folder), f"it holds {held}, not one of this study; use another --out")
    names = {f.name for f in dataclasses.fields(kind)}
    try:
        return kind.from_dict({k: v for k, v in record.items() if k in names})
    except (KeyError, TypeError, AttributeError) as err:
        why = f"not a run's config ({type(err).__name__}: {err})"
        raise bad_value("config", str(folder / "config.json"), why) from None


def read_evaluation(run: Run, episodes: int, seed: int) -> dict[str, Any] | None:
    """The run's evaluation.json if it measured its latest checkpoint on this episode set, else None."""
    from bitcomm.checkpoint import CHECKPOINTS, LATEST
    from bitcomm.learn.run_folder import read_json_object

    path, latest = run.folder / EVALUATION, run.folder / CHECKPOINTS / LATEST
    if not (path.is_file() and latest.is_file()):
        return None
    record = read_json_object(path)
    same = (record.get("checkpoint"), record.get("episodes"), record.get("seed"))
    return record if same == (_latest(run.folder)["checkpoint"], episodes, seed) else None


def lacking(record: dict[str, Any] | None) -> tuple[str, ...]:
    """The `PLAYS` an evaluation record lacks (all of them without one)."""
    return PLAYS if record is None else tuple(play for play in PLAYS if play not in record)


def missing_plays(run: Run, episodes: int, seed: int) -> tuple[str, ...]:
    """The `PLAYS` the run's evaluation of its latest checkpoint on this episode set lacks."""
    return lacking(read_evaluation(run, episodes, seed))


def _plays(run: Run, episodes: int, seed: int) -> dict[str, Callable[[], Any]]:
    """Each of `PLAYS` of the run's latest checkpoint on its own task, as a measurement to make."""
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.env_eval import evaluate_env
    from bitcomm.policies.evaluation import evaluate_checkpoint

    if isinstance(run.train, EnvTrainConfig):
        typed = run.train.env  # the spec typed on this `compare --env`: trusted as typed
        return {
            "sampled": lambda: evaluate_env(run.folder, episodes, seed, typed_env=typed),
            "greedy": lambda: evaluate_env(run.folder, episodes, seed, greedy=True, typed_env=typed),
            "cut": lambda: evaluate_env(run.folder, episodes, seed, drop_prob=1.0, typed_env=typed),
        }
    task = run.train.task
    cut = dataclasses.replace(task, channel=dataclasses.replace(task.channel, drop_prob=1.0))
    return {
        "sampled": lambda: evaluate_checkpoint(run.folder, episodes, seed),
        "greedy": lambda: evaluate_checkpoint(run.folder, episodes, seed, greedy=True),
        "cut": lambda: evaluate_checkpoint(run.folder, episodes, seed, task=cut),
    }


def evaluate_run(run: Run, episodes: int, seed: int) -> dict[str, Any]:
    """The plays its evaluation.json lacks of the latest checkpoint (every one of `PLAYS` for a new checkpoint),
    added to it; returns the record."""
    record = read_evaluation(run, episodes, seed) or {
        "checkpoint": _latest(run.folder)["checkpoint"],
        "episodes": episodes,
        "seed": seed,
    }
    measures = _plays(run, episodes, seed)
    record.update({play: measures[play]().to_dict() for play in lacking(record)})
    write_text_atomic(run.folder / EVALUATION, json.dumps(record, indent=2) + "\n")
    return record


STOP_GRACE_S = 60.0
"""How long an interrupted study waits for its running runs to save the batch they are on (a batch of a large grid
takes seconds) before it ends them at once; a second Ctrl-C ends them at once."""


_stopping: Any = None
"""In a study's worker: the study's flag (a shared byte) that it is stopping its runs (`stop_runs`)."""


def _init_worker(parent: int, stopping: Any = None) -> None:
    global _stopping
    _stopping = stopping
    # started deaf to the stop signals (`execute_all`): a Ctrl-C while it imported bitcomm printed a traceback, and
    # a SIGTERM of the group then killed it, breaking the pool
    # out of the study's process group: what signals the group (`timeout`, `kill -- -PGID`) reaches the parent alone,
    # which asks each run to save its batch (`stop_runs`); a SIGTERM of the group ended them at once, unsaved
    os.setpgrp()
    # an idle worker ignores Ctrl-C: one dying of it between runs would break the pool, which then ends the others
    # at once, saving or not (`execute` takes Ctrl-C while it works on a run); SIGTERM keeps its default, once a
    # group's copy that came while it started is dropped (`stop_runs` ends a worker with it)
    ignore_stop_signals()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

    import torch

    from bitcomm.worker_exit import end_with_parent

    end_with_parent(parent)  # a study killed alone must not leave its runs training
    torch.set_num_threads(1)  # parallel runs must not share (or fight over) thread pools


@contextlib.contextmanager
def made_for_the_run(folder: Path) -> Iterator[None]:
    """`folder`, and the folders above it that are missing, made for the block, and removed again where it ends in
    an error or a stop before the run wrote anything there: a study stopped as a run began left an empty folder
    for it (its `.lock` at most), which no later command needed."""
    from bitcomm.run_lock import LOCK

    made = [f for f in (folder, *folder.parents) if not f.exists()]  # the run's own first, then those above it
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise bad_value("out", str(folder), f"cannot create the run folder ({err.strerror or err})") from None
    try:
        yield
    except BaseException:
        for f in made:
            with contextlib.suppress(OSError):  # one that holds anything else stays
                if [entry.name for entry in f.iterdir()] == [LOCK]:
                    (f / LOCK).unlink()
                f.rmdir()
        raise


def execute(run: Run, eval_episodes: int, eval_seed: int) -> str:
    """Train (or resume) one run to its budget and evaluate it, holding the run folder's lock (one writer
    at a time, see `bitcomm.run_lock`); returns the status it was found in."""
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.env_run import train_env
    from bitcomm.learn.run import train
    from bitcomm.run_lock import run_lock

    # a study's worker, which ignores Ctrl-C while idle (`_init_worker`), takes it (or the parent's SIGINT, `stop_runs`)
    # while it works on a run: training stops after the batch it is on, saved, as `bitcomm train` does
    worker = multiprocessing.parent_process() is not None and signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    if worker:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        # asked to stop before it took Ctrl-C (starting, or between two runs): the signal was ignored, and the run
        # then trained on till the study ended it at once, `STOP_GRACE_S` later, unsaved
        if worker and _stopping is not None and _stopping.value:
            raise KeyboardInterrupt
        with made_for_the_run(run.folder), run_lock(run.folder):
            status = run_status(run)
            if status != "done":
                if isinstance(run.train, EnvTrainConfig):
                    train_env(run.train, run.folder, resume=status == "resume", progress=False)
                else:
                    train(run.train, run.folder, resume=status == "resume", progress=False)
            if missing_plays(run, eval_episodes, eval_seed):
                evaluate_run(run, eval_episodes, eval_seed)
    finally:
        if worker:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
    return status


def _processes_of(run: Run) -> int:
    """An a3c run counts as its workers."""
    return int(getattr(run.train, "workers", 1)) if getattr(run.train, "mode", "sync") == "a3c" else 1


def execute_all(
    runs: list[Run], cfg: CompareConfig | EnvCompareConfig, log: Callable[[str], None], describe: Describe
) -> None:
    """Every run that is not finished and evaluated, on up to `cfg.jobs` processes; `describe` gives the line
    logged for each."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    todo = [r for r in runs if run_status(r) != "done" or missing_plays(r, cfg.eval_episodes, cfg.eval_seed)]
    per_run = max((_processes_of(r) for r in todo), default=1)
    processes = max(1, min(len(todo), cfg.jobs // per_run))
    if not todo:
        log(f"{plural(len(runs), 'run', 'runs')}, all finished and evaluated")
        return
    workers = plural(processes, "process", "processes")
    done = len(runs) - len(todo)
    log(f"{plural(len(runs), 'run', 'runs')}, {done} finished and evaluated; {len(todo)} to go on {workers}")
    ctx = multiprocessing.get_context("spawn")
    stopping = ctx.Value("b", 0, lock=False)
    pool = ProcessPoolExecutor(processes, mp_context=ctx, initializer=_init_worker, initargs=(os.getpid(), stopping))
    # the repeats' guard is in place before any signal comes: `timeout`'s second copy, landing before the runs were
    # asked to stop, left the pool waiting on a run of hours
    with pool, sigterm_interrupts(), repeats_count_once():
        try:
            with deaf_children():  # the pool starts its processes as the runs are submitted
                futures = {pool.submit(execute, r, cfg.eval_episodes, cfg.eval_seed): r for r in todo}
            for k, future in enumerate(as_completed(futures), 1):
                run, status = futures[future], future.result()
                log(f"[{k}/{len(todo)}] {describe(run, status, cfg)}")
        except BaseException:  # Ctrl-C, SIGTERM or an alarm in this process only: stop the running runs
            # no public way before 3.14; taken before shutdown, which drops the pool's reference to its processes
            running = list((getattr(pool, "_processes", None) or {}).values())
            try:
                pool.shutdown(wait=False, cancel_futures=True)
            finally:
                stop_runs(running, stopping)  # a run's checkpoints are atomic: `bitcomm compare` again resumes it
            raise


def stop_runs(processes: list[Any], stopping: Any = None, grace_s: float | None = None) -> None:
    """Ask each worker to stop its run after the batch it is on and save it (SIGINT, as Ctrl-C would: the workers are
    out of the terminal's process group, `_init_worker`), and wait up to `grace_s` for them to end; then, or on a
    second interrupt (`bitcomm.stop_signals.repeats_count_once`), end them at once. Ended at once, a run stopped
    before its first checkpoint (every `checkpoint_seconds`) would start again from nothing. `stopping`, the workers'
    shared flag, is raised first: a worker that ignored the signal (it was starting, or between runs) starts no run.
    `grace_s` defaults to `STOP_GRACE_S`."""
    deadline = time.monotonic() + (STOP_GRACE_S if grace_s is None else grace_s)
    if stopping is not None:
        stopping.value = 1
    try:
        for process in processes:
            if process.is_alive():
                with contextlib.suppress(ProcessLookupError):  # it ended in between
                    os.kill(process.pid, signal.SIGINT)
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
    finally:
        for process in processes:
            if process.is_alive():
                process.terminate()


VERBS = {"new": "trained", "resume": "resumed", "done": "evaluated"}
"""What happened to a run, by the status it was found in."""


def describe(run: Run, status: str, cfg: CompareConfig) -> str:
    """One progress line for a finished run."""
    curve = read_curve(run.folder)
    evaluation = read_evaluation(run, cfg.eval_episodes, cfg.eval_seed) or {}
    verb = VERBS[status]
    sampled, cut = (evaluation.get(p, {}).get("mean_episode_length", math.nan) for p in ("sampled", "cut"))
    return (
        f"{run.configuration.name} seed {run.seed}: {verb} to {int(curve.episodes[-1])} episodes in "
        f"{curve.wall_s[-1]:.1f} s, rolling mean episode length {curve.length_rolling[-1]:.2f}, "
        f"evaluated {sampled:.2f} (sampled), {cut:.2f} with the channel cut"
    )


# ---------------------------------------------------------------------------------------------- results
class Curve(NamedTuple):
    """A run's learning curve, one entry per logged batch (metrics.csv)."""

    episodes: np.ndarray
    wall_s: np.ndarray
    length_rolling: np.ndarray
    length: np.ndarray
    team_return: np.ndarray


CURVE_COLUMNS = ("episode_length_rolling", "episode_length", "team_return")
"""The `charts/` columns of metrics.csv a `Curve` holds after episodes and wall_s (and curves.csv's names)."""


def read_columns(folder: Path, charts: tuple[str, ...]) -> list[np.ndarray]:
    """episodes, wall_s and the given `charts/` columns of a run's metrics.csv, as arrays; one line naming the run
    when the file is missing, empty, lacks a column, or has a row cut short or a cell that is not a number."""
    keys = ("episodes", "wall_s", *(f"charts/{c}" for c in charts))
    try:
        with (folder / "metrics.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            raise ValueError("it has no rows")
        for n, row in enumerate(rows, 2):  # line 1 is the header
            if None in row.values() or None in row:
                raise ValueError(f"line {n} has {'fewer' if None in row.values() else 'more'} cells than the header")
        return [np.array([float(r[k]) for r in rows]) for k in keys]
    except KeyError as err:
        raise ConfigError(f"invalid run={str(folder)!r}: metrics.csv has no column {err}") from None
    except (OSError, ValueError, csv.Error) as err:
        raise ConfigError(f"invalid run={str(folder)!r}: metrics.csv unreadable ({err})") from None


def read_curve(folder: Path) -> Curve:
    return Curve(*read_columns(folder, CURVE_COLUMNS))


def training_cut(run: Run) -> int:
    """The steps at which the run's training episodes are cut (`train_max_steps`, else the task's `max_steps`): its
    rolling length never exceeds it, so a level at or above it is met by the first batch, whatever was learned (a
    run without messages "reached" 2x an oracle that waits 16 steps for its goal, with 32-step episodes)."""
    return int(typing.cast("TrainConfig", run.train).training_task.env.max_steps)


def first_below(curve: Curve, level: float) -> dict[str, float] | None:
    """Episodes and training seconds when the rolling mean episode length first fell below `level`."""
    below = np.flatnonzero(curve.length_rolling < level)
    if below.size == 0:
        return None
    return {"episodes": int(curve.episodes[below[0]]), "wall_s": float(curve.wall_s[below[0]])}


def rolling_at(curve: Any, wall_s: float, field: str = "length_rolling") -> float:
    """The curve's `field` (default: the rolling mean episode length) at the last row logged at or before
    `wall_s` seconds of training."""
    rows = np.flatnonzero(curve.wall_s <= wall_s)
    return float(getattr(curve, field)[rows[-1] if rows.size else 0])


def budget_marks(episodes: int, first_logged: int = 1) -> list[int]:
    """The episodes at which a study's tables read every run's curve: `BUDGET_FRACTIONS` of the budget, none
    before `first_logged` (the latest first logged batch of the runs: before it a curve holds no value of its
    own, only its first batch's, so a tiny budget's marks there are moved to it)."""
    return sorted({max(1, first_logged, round(f * episodes)) for f in BUDGET_FRACTIONS})


def first_logged(curves: Iterable[Any]) -> int:
    """The episodes by which every one of `curves` has logged its first batch (`budget_marks`)."""
    return max(int(curve.episodes[0]) for curve in curves)


def rolling_at_episodes(curve: Any, episodes: int, field: str) -> float:
    """The curve's `field` at `episodes`, interpolated between the logged batches as the plotted curves are
    (the first batch's value before it, the last one's after it)."""
    return float(np.interp(episodes, curve.episodes, getattr(curve, field)))


def interval(values: list[float]) -> dict[str, Any] | None:
    """Mean and 95% interval over seeds (None for no values)."""
    if not values:
        return None
    mean, lo, hi = (float(x) for x in mean_interval(values))
    return {"mean": mean, "ci95": [lo, hi], "n": len(values)}


def oracle_result(task: TaskConfig, episodes: int, seed: int) -> EvalResult | None:
    """The oracle on the evaluation set (None where it cannot play: too few bits for the grid)."""
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.reference import OraclePolicy

    try:
        return evaluate(OraclePolicy(task), task, episodes, seed)
    except ConfigError:
        return None


def threshold_key(multiple: float) -> str:
    return f"{multiple:g}x"


def evaluation_of(run: Run, cfg: CompareConfig | EnvCompareConfig) -> dict[str, Any]:
    """The run's evaluation on the study's episode set; one line if it has none."""
    evaluation = read_evaluation(run, cfg.eval_episodes, cfg.eval_seed)
    if evaluation is None or lacking(evaluation):
        raise ConfigError(f"invalid run={str(run.folder)!r}: no evaluation of its latest checkpoint")
    return evaluation


def study_runs(runs: list[Run], cfg: CompareConfig | EnvCompareConfig, log: Callable[[str], None]) -> list[Run]:
    """The runs a call trains and reports: all of them, or with `cfg.report` those that have played their
    budget (one error line when none has)."""
    if not cfg.report:
        return runs
    finished = [r for r in runs if r.folder.is_dir() and run_status(r) == "done"]
    if not finished:
        raise bad_value("out", str(cfg.out), "holds no finished run of this study (--report trains nothing)")
    if len(finished) < len(runs):
        log(f"--report: {plural(len(runs) - len(finished), 'run', 'runs')} not finished, left out")
    return finished


def recipe_phrase(recipe: str, learning: dict[str, Any]) -> str:
    """The recipe a study ran and the learning options it set away from it ('reinforced recipe
    (anneal_move_entropy=false, train_max_steps=96)'), so that two studies' tables and figures tell apart what
    their commands did; bookkeeping a run may change on resume (`RESUMABLE`) is left out."""
    changed = sorted((k, v) for k, v in learning.items() if k not in RESUMABLE)
    return f"{recipe} recipe" + (f" ({', '.join(f'{k}={_format(v)}' for k, v in changed)})" if changed else "")


def seconds_phrase(seconds: float) -> str:
    """A table header's training time: whole seconds, or two figures below 10 s (a quick study's 0.3 s read "0 s")."""
    return f"{seconds:,.0f} s" if seconds >= 10 else f"{seconds:.2g} s"


def runs_phrase(study: dict[str, Any], configurations: list[dict[str, Any]]) -> str:
    """A table title's count of runs: '5 seeds x 60,000 episodes', or for a report whose configurations have
    finished fewer or different numbers of seeds, '2-5 of 5 seeds x 60,000 episodes (finished runs)'."""
    counts = sorted({len(c["runs"]) for c in configurations})
    seeds = plural(study["seeds"], "seed", "seeds")
    if len(counts) > 1 or counts[0] != study["seeds"]:
        seeds = (f"{counts[0]}" if len(counts) == 1 else f"{counts[0]}-{counts[-1]}") + f" of {seeds}"
    first = study.get("first_seed", 0)
    if first:
        seeds += f" ({first}..{first + study['seeds'] - 1})"
    return f"{seeds} x {study['episodes']:,} episodes" + (" (finished runs)" if study["report"] else "")


def run_record(
    run: Run, curve: Any, out: Path, equal_wall: float, marks: list[int], field: str, measure: str
) -> dict[str, Any]:
    """What every study's summary gives of a run: where it is, what it played, which machines trained it, and its
    curve's rolling `field` (named `measure`) at its end, at the study's equal wall-clock time and at the episodes
    `marks`."""
    from bitcomm.learn.run_folder import run_machines

    return {
        "seed": run.seed,
        "folder": str(run.folder.relative_to(out)),
        "machines": run_machines(run.folder),
        "episodes": int(curve.episodes[-1]),
        "wall_s": float(curve.wall_s[-1]),
        f"final_rolling_{measure}": float(getattr(curve, field)[-1]),
        "rolling_at_equal_wall": rolling_at(curve, equal_wall, field),
        "rolling_at_episodes": [rolling_at_episodes(curve, e, field) for e in marks],
    }


def machines_sentence(summary: dict[str, Any]) -> str:
    """table.md's word on where the seconds come from: one machine, or which machines and how many runs each (a
    run resumed elsewhere counts for each), since seconds compare only between runs of one machine."""
    from bitcomm.learn.run_folder import UNRECORDED

    counts = Counter(label for c in summary["configurations"] for r in c["runs"] for label in r["machines"])
    if list(counts) == [UNRECORDED]:
        return "The runs do not record their machines (made before bitcomm kept them)."
    if len(counts) == 1:
        return f"Every run ran on one machine ({next(iter(counts))})."
    parts = "; ".join(f"{label}: {plural(n, 'run', 'runs')}" for label, n in counts.items())
    return (
        f"The runs ran on {len(counts)} machines ({parts}): seconds compare only between runs of one machine "
        "(summary.json names each run's)."
    )


def along_budget(records: list[dict[str, Any]], marks: list[int]) -> list[dict[str, Any] | None]:
    """A configuration's runs' rolling curves at each of the episodes `marks`, as intervals over seeds."""
    return [interval([r["rolling_at_episodes"][i] for r in records]) for i in range(len(marks))]


def technique_entry(conf: Configuration) -> dict[str, Any]:
    """The first fields of a configuration's summary: what it trains."""
    estimator, messages = TECHNIQUES.get(conf.technique, TECHNIQUES["improved-bitwise"])
    return {
        "name": conf.name,
        "technique": conf.technique,
        "estimator": estimator,
        "messages": messages,
        "communication": conf.technique != NO_COMM,
    }


def summarize(
    cfg: CompareConfig, runs: list[Run], curves: dict[Path, Curve], oracle: dict[str, EvalResult | None]
) -> dict[str, Any]:
    """summary.json: the study, the oracle per task variant, and per configuration its runs and their intervals.

    Besides the end of the budget (equal episodes), every run is also read at the training time of the
    quickest run (equal wall-clock): a technique whose updates cost more has then played fewer episodes."""
    equal_wall = min(float(curves[r.folder].wall_s[-1]) for r in runs)
    first = runs[0].train
    marks = budget_marks(first.episodes, first_logged(curves[r.folder] for r in runs))
    configurations = []
    for conf in dict.fromkeys(r.configuration for r in runs):
        result = oracle[conf.task_variant]
        level = result.mean_episode_length if result is not None else None
        records, cut = [], training_cut(next(r for r in runs if r.configuration == conf))
        timed = {m: m * level for m in THRESHOLDS if level is not None and m * level < cut}  # the levels measured
        for run in (r for r in runs if r.configuration == conf):
            curve, evaluation = curves[run.folder], evaluation_of(run, cfg)
            record = run_record(run, curve, cfg.out, equal_wall, marks, "length_rolling", "episode_length")
            record.update({play: evaluation[play] for play in PLAYS})
            record["reached"] = {
                threshold_key(m): first_below(curve, timed[m]) if m in timed else None for m in THRESHOLDS
            }
            records.append(record)
        entry: dict[str, Any] = {
            **technique_entry(conf),
            "seeds": len(records),
            "values": dict(conf.values),
            "oracle_mean_episode_length": level,
            "wall_s": interval([r["wall_s"] for r in records]),
            "rolling_at_equal_wall": interval([r["rolling_at_equal_wall"] for r in records]),
            "rolling_at_episodes": along_budget(records, marks),
        }
        for play in PLAYS:
            entry[play] = {
                key: interval([r[play][key] for r in records])
                for key in ("mean_episode_length", "mean_team_return", "success_rate")
            }
        entry["reached"] = {} if level is not None else None
        for m in THRESHOLDS if level is not None else ():
            hits = [r["reached"][threshold_key(m)] for r in records if r["reached"][threshold_key(m)] is not None]
            entry["reached"][threshold_key(m)] = {
                "seeds": len(hits),
                "of": len(records),
                "episodes": interval([h["episodes"] for h in hits]),
                "wall_s": interval([h["wall_s"] for h in hits]),
                **({} if m in timed else {"above_cut": cut}),
            }
        entry["runs"] = records
        configurations.append(entry)
    return {
        "study": {
            "recipe": cfg.recipe,
            "episodes": first.episodes,
            "seeds": cfg.seeds,
            "first_seed": cfg.first_seed,
            "report": cfg.report,
            "techniques": list(cfg.techniques),
            "vary": {k: list(v) for k, v in cfg.vary.items()},
            "learning": dict(cfg.learning),
            "task": dataclasses.asdict(cfg.task),
            "eval_episodes": cfg.eval_episodes,
            "eval_seed": cfg.eval_seed,
            "thresholds": [threshold_key(m) for m in THRESHOLDS],
            "equal_wall_s": equal_wall,
            "episode_marks": marks,
        },
        "oracle": {variant: None if r is None else r.to_dict() for variant, r in oracle.items()},
        "configurations": configurations,
    }


# ---------------------------------------------------------------------------------------------- files
def write_curves_csv(
    runs: list[Run],
    curves: dict[Path, Any],
    varied: list[str],
    path: Path,
    curve_columns: tuple[str, ...] = CURVE_COLUMNS,
) -> None:
    """Every run's curve (a NamedTuple: episodes, wall_s, then `curve_columns`), at most CSV_POINTS rows each,
    with the configuration's `varied` values as columns."""
    columns = ["configuration", "technique", *varied, "seed", "episodes", "wall_s", *curve_columns]

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(columns)
            for run in runs:
                curve = curves[run.folder]
                n = len(curve.episodes)
                keep = np.unique(np.linspace(0, n - 1, min(n, CSV_POINTS)).round().astype(int))
                values = dict(run.configuration.values)
                for i in keep:
                    writer.writerow([run.configuration.name, run.configuration.technique,
                                     *(_format(values[v]) for v in varied), run.seed, int(curve.episodes[i]),
                                     *(float(a[i]) for a in curve[1:])])  # fmt: skip

    write_atomic(path, write)


def on_grid(curves: list[Any], field: str = "length_rolling") -> tuple[np.ndarray, np.ndarray]:
    """The seeds' curves' `field` (default: the rolling mean episode length) interpolated onto episodes every
    seed has reached."""
    lo, hi = max(c.episodes[0] for c in curves), min(c.episodes[-1] for c in curves)
    grid = np.linspace(lo, hi, GRID_POINTS) if hi > lo else np.array([hi])
    return grid, np.stack([np.interp(grid, c.episodes, getattr(c, field)) for c in curves])


def draw_seed_band(ax: Any, technique: str, seeds: list[Any], field: str = "length_rolling") -> list[np.ndarray]:
    """One technique's line on `ax`: the mean of its seeds' `field` with the 95% interval shaded, in the
    technique's own colour (the same in every bitcomm figure); returns the band's edges for axis scaling."""
    grid, values = on_grid(seeds, field)
    mean, lo, hi = mean_interval(values)
    color = f"C{CHOICES.index(technique)}"
    ax.plot(grid, mean, color=color, lw=1.4, label=f"{technique} ({plural(len(seeds), 'seed', 'seeds')})")
    ax.fill_between(grid, lo, hi, color=color, alpha=0.2, lw=0)
    return [lo, hi]


def plot_curves(
    runs: list[Run], curves: dict[Path, Curve], cfg: CompareConfig, oracle: dict[str, EvalResult | None], path: Path
) -> None:
    """One panel per variant (a shared y axis), a line per technique: mean over seeds with the 95% interval
    shaded; the oracle dashed."""
    from matplotlib.figure import Figure

    panels = {r.configuration.variant: r.configuration.task_variant for r in runs}
    cols = 2 if len(panels) == 4 else min(3, len(panels))
    rows = math.ceil(len(panels) / cols)
    fig = Figure(figsize=(5.4 * cols + 0.4, 3.8 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False, sharey=True).ravel()
    shown = []
    for ax, (variant, task_variant) in zip(axes, panels.items(), strict=False):
        for conf in dict.fromkeys(r.configuration for r in runs if r.configuration.variant == variant):
            shown += draw_seed_band(ax, conf.technique, [curves[r.folder] for r in runs if r.configuration == conf])
        result = oracle[task_variant]
        if result is not None:
            ax.axhline(result.mean_episode_length, color="k", ls="--", lw=1, label="oracle")
            shown.append(np.array([result.mean_episode_length]))
        ax.set_xlabel("environment episodes")
        ax.set_ylabel("mean episode length (rolling)")
        if variant:
            ax.set_title(variant, fontsize=9)
        ax.grid(alpha=0.3)
    if log_scale_suits(np.concatenate(shown)):
        axes[0].set_yscale("log")  # shared by every panel
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    labelled: dict[str, Any] = {}  # every panel's lines, once: the first panel may lack the oracle (too few bits)
    for ax in axes[: len(panels)]:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            labelled.setdefault(label, handle)
    axes[0].legend(list(labelled.values()), list(labelled), fontsize=8)
    recipe = recipe_phrase(cfg.recipe, cfg.learning)
    sep = ",\n" if "(" in recipe else ", "  # the options a study set, on a line of their own
    task = task_title(cfg.task, cfg.vary)
    fig.suptitle(f"{recipe}{sep if task else ''}{task}: mean and 95% interval over seeds", fontsize=10)
    save_figure(fig, path)


def markdown_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def markdown_header(header: list[str]) -> list[str]:
    """A Markdown table's first two lines: the column names and the separator."""
    return [markdown_row(header), "|" + "---|" * len(header)]


def per_seed_markdown(
    summary: dict[str, Any], describe: Callable[[dict[str, Any], dict[str, Any]], str], what: str
) -> list[str]:
    """table.md's section with one column per seed: `describe(configuration, run record)` in each cell."""
    seeds = sorted({r["seed"] for c in summary["configurations"] for r in c["runs"]})
    header = ["configuration", *(f"seed {s}" for s in seeds)]
    lines = ["", "## Per seed", "", what, "", *markdown_header(header)]
    for c in summary["configurations"]:
        by_seed = {r["seed"]: describe(c, r) for r in c["runs"]}
        lines.append(markdown_row([c["name"], *(by_seed.get(s, "—") for s in seeds)]))
    return lines


def along_budget_markdown(summary: dict[str, Any], measure: str, fmt: str) -> list[str]:
    """table.md's section reading every configuration's rolling `measure` at the study's episode marks."""
    marks = summary["study"]["episode_marks"]
    header = ["configuration", *(plural(e, "episode", "episodes", grouped=True) for e in marks)]
    lines = [
        "",
        f"## Rolling {measure} along the budget",
        "",
        f"Each run's rolling {measure} of its training episodes at these episodes (interpolated between logged "
        "batches, as the curves are drawn); mean ± the 95% half-interval over seeds.",
        "",
        *markdown_header(header),
    ]
    for c in summary["configurations"]:
        lines.append(markdown_row([c["name"], *(cell(v, fmt) for v in c["rolling_at_episodes"])]))
    return lines


def _seed_cell(configuration: dict[str, Any], run: dict[str, Any]) -> str:
    """A grid run's final lengths, sampled (greedy; channel cut), and when its rolling length first fell below
    each level."""
    lengths = [run[play]["mean_episode_length"] for play in PLAYS]
    text = "{:.2f} ({:.1f}; {:.1f})".format(*lengths)
    if configuration["oracle_mean_episode_length"] is None:
        return text
    for key, hit in run["reached"].items():
        untimed = "above_cut" in configuration["reached"][key]
        text += f"; {key}: " + (
            "above the cut" if untimed else "—" if hit is None else f"{hit['episodes']:,} ep, {hit['wall_s']:,.0f} s"
        )
    return text


def cell(value: dict[str, Any] | None, fmt: str) -> str:
    if value is None:
        return "—"
    lo, hi = value["ci95"]
    return f"{value['mean']:{fmt}}" if value["n"] < 2 else f"{value['mean']:{fmt}} ± {(hi - lo) / 2:{fmt}}"


def _reached_cell(reached: dict[str, Any] | None, what: str, fmt: str) -> str:
    if reached is None:
        return "no oracle"
    if "above_cut" in reached:
        return f"above the {reached['above_cut']}-step training cut"
    if not reached["seeds"]:
        return f"not reached (0/{reached['of']})"
    return f"{cell(reached[what], fmt)} ({reached['seeds']}/{reached['of']})"


def task_sentence(study: dict[str, Any]) -> str:
    """table.md's words for a study's task: the options it holds, then the values of those it varies (the base value
    of a varied option, which no run played, is left out)."""
    held = task_title(TaskConfig.from_dict(study["task"]), study["vary"])
    return held + "".join(f"; varied {k}: {', '.join(_format(x) for x in v)}" for k, v in study["vary"].items())


def table_markdown(summary: dict[str, Any]) -> str:
    """table.md: one row per configuration (and the oracle per variant), mean ± 95% half-interval over seeds."""
    study = summary["study"]
    keys = study["thresholds"]
    header = ["configuration", "seeds", "length (sampled)", "return (sampled)", "length (greedy)", "return (greedy)",
              "length, channel cut at evaluation", *(f"episodes to {k} oracle" for k in keys),
              *(f"seconds to {k} oracle" for k in keys), "seconds per run",
              f"rolling length after {seconds_phrase(study['equal_wall_s'])}"]  # fmt: skip
    lines = [
        f"# bitcomm compare: {recipe_phrase(study['recipe'], study['learning'])}, "
        f"{runs_phrase(study, summary['configurations'])}",
        "",
        f"Task: {task_sentence(study)}. Evaluation: {study['eval_episodes']} episodes of seed {study['eval_seed']}: "
        "sampled, greedy, and sampled with every message dropped (the channel cut: what the same policy does without "
        "communication).",
        "Each cell is the mean ± the 95% half-interval over seeds (Student t); (k/n): the seeds that reached the "
        "level, averaged over those; seconds are training wall time, with runs sharing the machine's cores. The "
        "last column reads every run's rolling mean at the quickest run's training time (equal wall-clock). "
        + machines_sentence(summary),
        "",
        *markdown_header(header),
    ]
    for variant, result in summary["oracle"].items():
        if result is not None:
            cells = [f"{result['mean_episode_length']:.2f}", f"{result['mean_team_return']:.2f}"] * 2
            lines.append(markdown_row([f"oracle {variant}".strip(), "—", *cells, *["—"] * (2 * len(keys) + 3)]))
    for c in summary["configurations"]:
        reached = [c["reached"][k] if c["reached"] is not None else None for k in keys]
        cells = [c["name"], str(c["seeds"])]
        for play in ("sampled", "greedy"):
            cells += [cell(c[play]["mean_episode_length"], ".2f"), cell(c[play]["mean_team_return"], ".2f")]
        cells.append(cell(c["cut"]["mean_episode_length"], ".2f"))
        for what, fmt in (("episodes", ",.0f"), ("wall_s", ",.1f")):
            cells += [_reached_cell(r, what, fmt) for r in reached]
        cells += [cell(c["wall_s"], ",.1f"), cell(c["rolling_at_equal_wall"], ".2f")]
        lines.append(markdown_row(cells))
    lines += per_seed_markdown(
        summary,
        _seed_cell,
        "Length of each run's final policy, sampled (greedy; channel cut), on the evaluation episodes; then the "
        "training episodes and seconds at which its rolling length first fell below each level (—: never; above the "
        "cut: a level no shorter than training's episodes, which every rolling length is below).",
    )
    lines += along_budget_markdown(summary, "length", ".2f")
    return "\n".join(lines) + "\n"


def run_compare(cfg: CompareConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train what is missing, then write curves.csv, curves.png/.svg, table.md and summary.json; returns the summary."""
    runs = study_runs(plan(cfg), cfg, log)
    cfg.out.mkdir(parents=True, exist_ok=True)
    tasks = {r.configuration.task_variant: variant_task(cfg, r.configuration.values) for r in runs}
    oracle = {variant: oracle_result(task, cfg.eval_episodes, cfg.eval_seed) for variant, task in tasks.items()}
    execute_all(runs, cfg, log, describe)
    curves = {r.folder: read_curve(r.folder) for r in runs}
    summary = summarize(cfg, runs, curves, oracle)
    write_curves_csv(runs, curves, list(cfg.vary), cfg.out / "curves.csv")
    plot_curves(runs, curves, cfg, oracle, cfg.out / "curves.png")
    write_text_atomic(cfg.out / "table.md", table_markdown(summary))
    write_text_atomic(cfg.out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
