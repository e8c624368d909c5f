"""`bitcomm compare`: the four techniques and a no-communication baseline over seeds (see `bitcomm.studies.compare`).

Task flags and learning flags are those of `bitcomm train` and apply to every run; `--vary NAME=V1,V2`
(repeatable) makes one configuration per technique and value. Running the same command again skips
finished runs and resumes interrupted ones; with `--report` it trains nothing and reports the finished
runs. With `--env PACKAGE.MODULE:FACTORY` the study runs on that PettingZoo env wrapped in bitcomm's
channel (`bitcomm.studies.env_compare`), with `bitcomm train --env`'s flags.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import typing
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bitcomm.commands import env_train
from bitcomm.commands.common import add_task_flags, task_from_args, write_provenance
from bitcomm.commands.env_flags import add_env_flags
from bitcomm.commands.flags import (
    EVAL_EPISODES,
    MAX_JOBS,
    MAX_TRAIN_EPISODES,
    SEED,
    check_eval,
    check_train,
    integer,
    out_dir,
)
from bitcomm.commands.learning_flags import add_learning_flags, learning_overrides
from bitcomm.errors import bad_value
from bitcomm.learn.recipes import DEFAULT_RECIPE, RECIPES
from bitcomm.studies.compare import (
    CHOICES,
    ENV_STUDY_SEEDS,
    GRID_STUDY_SEEDS,
    STUDY_EPISODES,
    CompareConfig,
    parse_techniques,
    parse_vary,
    run_compare,
)

if TYPE_CHECKING:
    from bitcomm.learn.config import TrainConfig
    from bitcomm.learn.env_config import EnvTrainConfig

MAX_SEEDS = 1000
"""Seeds per configuration: 1000 runs of each is already months of CPU (and keeps --eval-seed's default free)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    from bitcomm.policies.source import mark_task_defaults

    p = sub.add_parser(
        "compare",
        help="train the four techniques and a no-communication baseline over seeds: curves, table, summary",
        description="Train every technique (standard|improved x onehot|bitwise) and a learned baseline whose "
        "messages are all dropped, over several seeds at one budget; evaluate each run and the oracle on one "
        "episode set; write curves.csv, curves.png/.svg, table.md and summary.json to --out.",
    )
    p.add_argument(
        "--techniques",
        type=str,
        default=None,
        metavar="A,B,...",
        help=f"a subset of {', '.join(CHOICES)} (default: all)",
    )
    p.add_argument(
        "--recipe", choices=tuple(RECIPES), default=None, help=f"learning options (default {DEFAULT_RECIPE}; grid only)"
    )
    p.add_argument(
        "--seeds",
        type=integer(1, MAX_SEEDS),
        default=None,
        help=f"seeds F..F+S-1 per configuration, F the --first-seed (default {GRID_STUDY_SEEDS}; with --env "
        f"{ENV_STUDY_SEEDS})",
    )
    p.add_argument(
        "--first-seed",
        type=SEED,
        default=0,
        help="the first training seed (default %(default)s): a study split across machines, or one whose later "
        "seeds are added elsewhere, trains seeds F..F+S-1 into the same layout and reports them",
    )
    p.add_argument(
        "--episodes",
        type=integer(1, MAX_TRAIN_EPISODES),
        default=None,
        help=f"budget of every run, at least one batch (default {STUDY_EPISODES}; with --env, that of bitcomm train "
        "--env)",
    )
    p.add_argument(
        "--jobs", type=integer(1, MAX_JOBS), default=None, help="processes at once (default: the core count)"
    )
    p.add_argument("--out", type=out_dir, default=Path("runs/compare"), help="study folder (default %(default)s)")
    p.add_argument(
        "--eval-episodes", type=EVAL_EPISODES, default=1000, help="evaluation episodes per run (default %(default)s)"
    )
    p.add_argument(
        "--eval-seed",
        type=SEED,
        default=1000,
        help="seed of the evaluation episodes, not a training seed (default %(default)s)",
    )
    p.add_argument(
        "--vary",
        action="append",
        default=[],
        metavar="NAME=V1,V2,...",
        help="a learning or task option to vary, e.g. flip_prob=0,0.05,0.1 (repeatable; configurations are "
        "techniques x the product of the values; a varied option overrides its flag)",
    )
    p.add_argument(
        "--report",
        action="store_true",
        help="train nothing: write the tables from the runs in --out that have played their budget (evaluating "
        "what their evaluation lacks), leaving out the others",
    )
    p.add_argument("--json", action="store_true", help="print summary.json instead of the table")
    add_learning_flags(p)
    add_task_flags(p)
    add_env_flags(p)
    mark_task_defaults(p)  # a grid-only flag typed with --env is refused
    p.set_defaults(run=run)


def check_study(cfg: CompareConfig) -> None:
    """Every run's config built (a bad learning option or varied value fails now) and its memory checked,
    `jobs` of them at once, before the first run starts."""
    from bitcomm.studies.compare import plan

    runs = plan(cfg)
    for r in runs:
        train = typing.cast("TrainConfig", r.train)  # a grid study's runs are on the grid
        check_train(train, processes=min(cfg.jobs, len(runs)))
        check_eval(train.task, cfg.eval_episodes, train.model.messages == "onehot", "eval-episodes")


def _common(args: argparse.Namespace) -> dict[str, Any]:
    """The study options every study has."""
    return {
        "out": args.out,
        "techniques": parse_techniques(args.techniques) if args.techniques is not None else CHOICES,
        "jobs": args.jobs if args.jobs is not None else os.cpu_count() or 1,
        "eval_episodes": args.eval_episodes,
        "eval_seed": args.eval_seed,
        "first_seed": args.first_seed,
        "report": args.report,
    }


def grid_study(args: argparse.Namespace) -> tuple[Callable[..., dict[str, Any]], Callable[..., str], Any]:
    from bitcomm.studies.compare import table_markdown

    env_train.check_env_only(args)
    vary = dict(parse_vary(text) for text in args.vary)
    if len(vary) != len(args.vary):
        raise bad_value("vary", args.vary, "each NAME at most once")
    cfg = CompareConfig(
        **_common(args),
        recipe=args.recipe or DEFAULT_RECIPE,
        seeds=args.seeds or GRID_STUDY_SEEDS,
        episodes=args.episodes or STUDY_EPISODES,
        task=task_from_args(args),
        learning=learning_overrides(args),
        vary=vary,
    )
    check_study(cfg)
    return run_compare, table_markdown, cfg


def env_study(args: argparse.Namespace) -> tuple[Callable[..., dict[str, Any]], Callable[..., str], Any]:
    """The study on a wrapped env; the grid's --recipe and --vary do not apply (one line each)."""
    from bitcomm.studies.env_compare import EnvCompareConfig, plan, run_env_compare, table_markdown

    for name in ("recipe", "vary"):
        if getattr(args, name):
            raise bad_value(name, getattr(args, name), "a grid option, not used with --env")
    base = env_train.env_config_from_args(args)
    cfg = EnvCompareConfig(base=base, **_common(args), seeds=args.seeds or ENV_STUDY_SEEDS)
    runs = plan(cfg)
    configs = [typing.cast("EnvTrainConfig", r.train) for r in runs]
    env_train.check_env(configs, processes=min(cfg.jobs, len(runs)), eval_episodes=cfg.eval_episodes)
    return run_env_compare, table_markdown, cfg


def run(args: argparse.Namespace) -> int:
    study, table_markdown, cfg = env_study(args) if args.env is not None else grid_study(args)
    progress = sys.stderr if args.json else sys.stdout
    summary = study(cfg, log=lambda line: print(line, file=progress, flush=True))
    write_provenance(args, cfg.out)
    if args.json:
        json.dump(summary, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print()
    print(table_markdown(summary), end="")
    print(f"\nwrote {cfg.out}/curves.csv, curves.png, curves.svg, table.md, summary.json and provenance.json")
    return 0
