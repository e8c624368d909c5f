"""`bitcomm variance RUN_OR_CHECKPOINT...`: the two estimators' gradient variance at fixed policies (see
`bitcomm.studies.variance`), at the stages of a run kept in its `checkpoints/` folder."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from bitcomm.commands.common import add_task_flags, write_provenance
from bitcomm.commands.flags import (
    MAX_BATCH,
    MAX_REPEATS,
    SEED,
    add_threads_flag,
    check_play,
    integer,
    number,
    out_dir,
    use_threads,
)
from bitcomm.errors import bad_value, plural
from bitcomm.files import write_text_atomic
from bitcomm.stop_signals import sigterm_interrupts
from bitcomm.studies.tables import task_title

if TYPE_CHECKING:
    from bitcomm.config import TaskConfig
    from bitcomm.studies.variance import VarianceConfig


def add_parser(sub: argparse._SubParsersAction) -> None:
    # defaults written out (the same as VarianceConfig's, checked by a test): importing bitcomm.studies.variance
    # here would load torch for every command of the CLI
    from bitcomm.policies.source import mark_task_defaults

    p = sub.add_parser(
        "variance",
        help="variance of the standard and improved gradient estimators along a run (CSV, Markdown, PNG)",
        description="At each checkpoint (policy frozen) fit a V1 and a V2 critic to the Monte Carlo returns, then "
        "compare the standard (eq. 7) and improved (eq. 8) policy-gradient estimates of many independent batches: "
        "trace of their covariance for the message and the action part, ratio improved/standard, and the cosine "
        "between their mean gradients. Task flags change the task the policy is measured on (e.g. --delay).",
    )
    p.add_argument(
        "paths", nargs="+", metavar="RUN_OR_CHECKPOINT", help="run folders (their kept checkpoints) or .safetensors"
    )
    p.add_argument(
        "--stages",
        default="all",
        help="checkpoints of each run folder: all, latest, spread:N (N evenly spread) or episode counts E1,E2,... "
        "(default %(default)s)",
    )
    p.add_argument(
        "--batches", type=integer(2, MAX_REPEATS), default=64, help="batches compared per stage (default %(default)s)"
    )
    p.add_argument(
        "--num-envs", type=integer(1, MAX_BATCH), default=32, help="episodes per batch (default %(default)s)"
    )
    p.add_argument(
        "--fit-batches",
        type=integer(0, MAX_REPEATS),
        default=100,
        help="most batches to fit the critics on (default %(default)s)",
    )
    p.add_argument(
        "--fit-steps", type=integer(1, MAX_REPEATS), default=4, help="critic steps per fit batch (default %(default)s)"
    )
    p.add_argument(
        "--plateau",
        type=number(0.0, 1.0),
        default=0.01,
        help="stop fitting once the held-out critic loss improves by less than this fraction (0: never; "
        "default %(default)s)",
    )
    p.add_argument("--seed", type=SEED, default=0, help="seed of critics, episodes and sampling (default %(default)s)")
    p.add_argument(
        "--out", type=out_dir, default="variance", help="folder for variance.csv/.md/.png/.svg (default %(default)s)"
    )
    p.add_argument("--json", action="store_true", help="print the rows as one JSON list")
    add_threads_flag(p)
    add_task_flags(p, reads_runs=True)
    mark_task_defaults(p)
    p.set_defaults(run=run)


def variance_config(args: argparse.Namespace) -> VarianceConfig:
    from bitcomm.studies.variance import VarianceConfig

    return VarianceConfig(
        batches=args.batches,
        num_envs=args.num_envs,
        fit_batches=args.fit_batches,
        fit_steps=args.fit_steps,
        plateau=args.plateau,
        seed=args.seed,
    )


def check_once(files: list[Path]) -> None:
    """One line for a checkpoint named twice (a run given twice, or a run folder and one of its files): it was
    measured twice and its rows printed twice, as a repeated --stages count would be."""
    seen: dict[str, Path] = {}
    for file in files:
        key = os.path.realpath(file)
        if key in seen:
            raise bad_value("RUN_OR_CHECKPOINT", str(file), f"{seen[key]} is measured already; give each once")
        seen[key] = file


def check_one_task(files: list[Path], tasks: list[TaskConfig]) -> None:
    """One line for checkpoints of different tasks: the title, the plot and provenance.json name one task, which
    was the last one's (a 4x4 run's rows were titled 5x5)."""
    for file, task in zip(files, tasks, strict=True):
        if task != tasks[0]:
            theirs, first = task_title(task), task_title(tasks[0])
            what = f"its task ({theirs}) is not" if theirs != first else f"its task ({theirs}) differs from"
            raise bad_value(
                "RUN_OR_CHECKPOINT",
                str(file),
                f"{what} {files[0]}'s ({first}); one table measures one task: run bitcomm variance once per task",
            )


@sigterm_interrupts()  # from its first line: `timeout` or a scheduler stops it as Ctrl-C does, exit 143
def run(args: argparse.Namespace) -> int:
    from bitcomm.policies.source import CRITIC_INPUTS, resolve_task
    from bitcomm.studies.variance import (
        load_stage,
        markdown_table,
        measure_stage,
        parse_stages,
        plot_variance,
        select_stages,
        write_csv,
    )

    vcfg = variance_config(args)
    stages = parse_stages(args.stages)
    files = []
    for path in args.paths:  # fail early, before measuring
        picked = select_stages(path, stages)
        if isinstance(stages, int) and len(picked) < stages:  # a run folder keeps only so many checkpoints
            kept = plural(len(picked), "checkpoint", "checkpoints")
            print(f"{path}: spread:{stages} measures the {kept} it keeps", file=sys.stderr)
        files += picked
    check_once(files)
    loaded = [load_stage(f) for f in files]  # each read once: its task checked here, its policy measured below
    tasks = [
        resolve_task(args, s.config.task, label=f"checkpoint {str(f)!r}", fixed=CRITIC_INPUTS)
        for f, s in zip(files, loaded, strict=True)
    ]
    check_one_task(files, tasks)
    use_threads(args)
    rows, task = [], None
    for file, stage, task in zip(files, loaded, tasks, strict=True):
        check_play(task, "num-envs", vcfg.num_envs, vcfg.num_envs, task.env.max_steps)
        stage_rows = measure_stage(stage.on_task(task), vcfg)
        rows += stage_rows
        if not args.json:
            message = next(r for r in stage_rows if r.part == "message")
            print(f"{file}: message variance ratio improved/standard {message.ratio:.3f}", file=sys.stderr)
    assert task is not None
    title = task_title(task)
    out = Path(args.out)
    csv_path = write_csv(rows, out / "variance.csv")
    md_path = out / "variance.md"
    write_text_atomic(md_path, markdown_table(rows, f"Gradient variance of the two estimators: {title}"))
    figures = plot_variance(rows, out / "variance.png", title)
    write_provenance(args, out, task)
    if args.json:
        json.dump([r.to_dict() for r in rows], sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(markdown_table(rows), end="")
    print(f"wrote {csv_path}, {md_path}, {', '.join(map(str, figures))} and provenance.json")
    return 0
