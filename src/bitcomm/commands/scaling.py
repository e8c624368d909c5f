"""`bitcomm scaling`: bitwise against one-hot messages as the grid grows (see `bitcomm.studies.scaling`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from bitcomm.commands.common import write_provenance
from bitcomm.commands.flags import (
    MAX_BATCH,
    MAX_REPEATS,
    MAX_TRAIN_EPISODES,
    SEED,
    add_threads_flag,
    integer,
    number,
    out_dir,
    use_threads,
)
from bitcomm.learn.recipes import DEFAULT_RECIPE, RECIPES

if TYPE_CHECKING:
    from bitcomm.studies.scaling import ScalingConfig


MAX_SCALING_SIZE = 128
"""Largest grid side measured: K = 14 bits, 16,384 one-hot outputs; a side of 1000 (K = 20) took hours."""
MAX_BATCH_EPISODES = 4096
MAX_BATCH_STEPS = 1024
"""The timed batch: 4096 episodes of 1024 steps is already gigabytes on the largest grid."""


def sizes(text: str) -> str:
    """An argparse type: comma-separated grid sides in [2, MAX_SCALING_SIZE], each once (kept as text for
    ScalingConfig); a side given twice would only measure it twice and print its rows twice."""
    allowed = f"must be comma-separated grid sides, each an integer in [2, {MAX_SCALING_SIZE}]"
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: {allowed}") from None
    if not values or not all(2 <= v <= MAX_SCALING_SIZE for v in values):
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: {allowed}")
    repeated = next((v for i, v in enumerate(values) if v in values[:i]), None)
    if repeated is not None:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: grid side {repeated} is repeated; give each once")
    return text


def add_parser(sub: argparse._SubParsersAction) -> None:
    # defaults written out (the same as ScalingConfig's, checked by a test): importing bitcomm.studies.scaling
    # here would load torch for every command of the CLI
    p = sub.add_parser(
        "scaling",
        help="output size, parameters, memory and update time of bitwise vs one-hot heads by grid size",
        description="For each grid side S (K = ceil(log2(S^2)) bits) and each message head: message outputs (K vs "
        "2^K), parameters of the policy and both critics, parameter bytes, peak memory of one learner update "
        "(torch profiler, CPU) and its time on a fixed small batch; optionally a training run per pair "
        "(--episodes). Writes scaling.csv, scaling.md and scaling.png/.svg.",
    )
    p.add_argument(
        "--sizes",
        type=sizes,
        default="10,16,32,64",
        help=f"grid sides, each in [2, {MAX_SCALING_SIZE}] (default %(default)s)",
    )
    p.add_argument(
        "--recipe", choices=tuple(RECIPES), default=DEFAULT_RECIPE, help="networks and update (default %(default)s)"
    )
    p.add_argument("--estimator", choices=("improved", "standard"), default="improved", help="(default %(default)s)")
    p.add_argument(
        "--batch-episodes",
        type=integer(1, MAX_BATCH_EPISODES),
        default=8,
        help="episodes in the timed batch (default %(default)s)",
    )
    p.add_argument(
        "--batch-steps",
        type=integer(1, MAX_BATCH_STEPS),
        default=32,
        help="their truncation length (default %(default)s)",
    )
    p.add_argument(
        "--repeats", type=integer(1, MAX_REPEATS), default=5, help="timed updates, median taken (default %(default)s)"
    )
    p.add_argument(
        "--episodes",
        type=integer(0, MAX_TRAIN_EPISODES),
        default=0,
        help="training budget per size and head for learning curves; 0 skips training; a run already in --out is "
        "kept, or resumed to a larger budget (default %(default)s)",
    )
    p.add_argument(
        "--num-envs",
        type=integer(1, MAX_BATCH),
        default=None,
        help="episodes per training batch (default: the recipe's)",
    )
    p.add_argument(
        "--max-memory-gb",
        type=number(0.0, 1e6, strict=True),
        default=8.0,
        help="train only pairs whose estimated training update fits (default %(default)s)",
    )
    p.add_argument("--seed", type=SEED, default=0, help="seed of the networks, batch and runs (default %(default)s)")
    p.add_argument(
        "--out", type=out_dir, default="scaling", help="folder for scaling.csv/.md/.png/.svg (default %(default)s)"
    )
    p.add_argument("--json", action="store_true", help="print the rows as one JSON list")
    add_threads_flag(p, "; the update times depend on them, so scaling.md records the count")
    p.set_defaults(run=run)


def scaling_config(args: argparse.Namespace) -> ScalingConfig:
    from bitcomm.studies.scaling import ScalingConfig, parse_sizes

    return ScalingConfig(
        sizes=parse_sizes(args.sizes),
        recipe=args.recipe,
        estimator=args.estimator,
        batch_episodes=args.batch_episodes,
        batch_steps=args.batch_steps,
        repeats=args.repeats,
        episodes=args.episodes,
        num_envs=args.num_envs,
        max_memory_gb=args.max_memory_gb,
        seed=args.seed,
    )


def threads_note(threads: int, chosen: str) -> str:
    """The line scaling.md ends with: the torch threads the updates ran on, and what chose them."""
    return f"\nUpdates timed on {threads} torch thread{'s' if threads != 1 else ''} ({chosen}).\n"


def run(args: argparse.Namespace) -> int:
    import torch

    from bitcomm.studies.scaling import markdown_table, plot_curves, plot_scaling, run_scaling, write_csv

    scfg = scaling_config(args)
    out = Path(args.out)
    threads = use_threads(args)
    chosen = "--threads" if args.threads else "OMP_NUM_THREADS" if threads is None else "the idle cores"
    rows = run_scaling(scfg, out, progress=not args.json)
    csv_path = write_csv(rows, out / "scaling.csv")
    md_path = out / "scaling.md"
    table = markdown_table(rows, scfg) + threads_note(torch.get_num_threads(), chosen)
    md_path.write_text(table)
    written = [csv_path, md_path, *plot_scaling(rows, out / "scaling.png"), *plot_curves(out, rows)]
    written.append(write_provenance(args, out))
    if args.json:
        json.dump([r.to_dict() for r in rows], sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(table, end="")
    print("wrote " + ", ".join(map(str, written)))
    return 0
