"""`bitcomm sweep [RUN] [--policy oracle]... [--param NAME=V1,V2,...]...`: robustness curves
(see `bitcomm.studies.sweep`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bitcomm.commands.common import add_task_flags, write_provenance
from bitcomm.commands.flags import EVAL_EPISODES, SEED, add_threads_flag, check_eval, out_dir, use_threads
from bitcomm.config import TaskConfig
from bitcomm.errors import bad_value
from bitcomm.policies.source import add_policy_flags, sources_from_args
from bitcomm.stop_signals import sigterm_interrupts
from bitcomm.studies.sweep import DEFAULT_SWEEP, SWEEPABLE, parse_param, plot_sweep, run_sweep, with_param, write_csv
from bitcomm.studies.tables import task_title


def add_parser(sub: argparse._SubParsersAction) -> None:
    defaults = " ".join(f"{k}={','.join(str(v) for v in vs)}" for k, vs in DEFAULT_SWEEP.items())
    p = sub.add_parser(
        "sweep",
        help="mean episode length against actuation and channel noise (CSV, PNG and SVG)",
        description="Vary one parameter at a time from the task given by the flags (or RUN's task) and evaluate "
        f"each policy on the same episodes. Parameters: {', '.join(SWEEPABLE)}. Default: {defaults}.",
    )
    p.add_argument(
        "--param",
        action="append",
        default=None,
        metavar="NAME=V1,V2,...",
        help="a parameter to sweep (repeatable; default: the description's)",
    )
    p.add_argument("--episodes", type=EVAL_EPISODES, default=1000, help="episodes per point (default %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the episode set (default %(default)s)")
    p.add_argument(
        "--out",
        type=out_dir,
        default="sweep",
        help="folder for sweep.csv, sweep.png and sweep.svg (default %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="print the points as one JSON list")
    add_threads_flag(p)
    add_task_flags(p, reads_runs=True)
    add_policy_flags(p, several=True)
    p.set_defaults(run=run)


def check_points(task: TaskConfig, params: dict[str, tuple[float, ...]], episodes: int, onehot: bool = False) -> None:
    """Every point's task built (so a bad value fails now, not after the points before it) and its memory
    (`onehot`: a policy swept sends one-hot messages)."""
    for name, values in params.items():
        for value in values:
            check_eval(with_param(task, name, value), episodes, onehot)


@sigterm_interrupts()  # from its first line: `timeout` or a scheduler stops it as Ctrl-C does, exit 143
def run(args: argparse.Namespace) -> int:
    episodes = args.episodes
    params = dict(parse_param(text) for text in args.param) if args.param else dict(DEFAULT_SWEEP)
    if args.param and len(params) != len(args.param):  # a second --param NAME=... would replace the first's values
        raise bad_value("param", args.param, "each NAME at most once (its values in one --param NAME=V1,V2,...)")
    sources = sources_from_args(args)
    task = sources[0].task_from_args(args)  # a learned policy's task when RUN is given; others join it
    check_points(task, params, episodes, any(source.onehot() for source in sources))
    use_threads(args)
    points = run_sweep(sources, task, params, episodes, args.seed)
    out = Path(args.out)
    csv_path = write_csv(points, out / "sweep.csv")
    figures = plot_sweep(points, out / "sweep.png", f"from {task_title(task)}")  # each panel varies one of it
    write_provenance(args, out, task)
    if args.json:
        json.dump([p.row() for p in points], sys.stdout)
        sys.stdout.write("\n")
        return 0
    for p in points:
        lo, hi = p.result.ci95
        print(f"{p.policy:>10}  {p.param}={p.value:<6g} mean episode length {p.result.mean_episode_length:7.2f} "
              f"(95% CI {lo:.2f}-{hi:.2f}), success {p.result.success_rate:.3f}")  # fmt: skip
    print(f"wrote {csv_path}, {', '.join(map(str, figures))} and provenance.json")
    return 0
