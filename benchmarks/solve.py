"""The yardstick of issues 4 and 16: how fast does a recipe learn the task, seed by seed?

Trains a named recipe (improved + bitwise unless told otherwise) on a task for S seeds and prints,
per seed, the environment episodes and training wall seconds until the mean episode length of
sampled play falls below 2x, 1.5x and 1.15x the oracle, and then until greedy play falls below 1.05x
(the ladder's third rung). The oracle is its mean on the fixed episodes below, the ones that confirm the rungs. A
sampled rung counts when the rolling mean over the last 1,000 training episodes is below it AND `bitcomm eval` on
2,000 fixed episodes (sampled, seed 12345) confirms it;
the greedy rung is checked with `bitcomm eval --greedy` after every chunk once 1.15x is reached.
Training runs in chunks of `--chunk` episodes, each one resuming the run's checkpoint, so the
checks happen between chunks; evaluation time is not counted as training time. A run whose weights become NaN
or infinite stops there (`"diverged"` in its result says when) and is measured at its last checkpoint.
Seeds run `--jobs` at a time, each in its own process with `--threads` torch threads.
The last line printed is one JSON object.

The default recipe decays its learning rates over the budget, so it needs `--max-episodes` (the
schedule's horizon, shared by all chunks of a seed).

    python benchmarks/solve.py --size 4 --bits 4 --minutes 1 --max-episodes 30000     # rung 1
    python benchmarks/solve.py --minutes 15 --max-episodes 200000 --chunk 8192        # rung 2 (the paper's 10x10)
    python benchmarks/solve.py --minutes 15 --max-episodes 200000 --threads 2 --jobs 1  # each seed alone on 2 cores
    python benchmarks/solve.py --recipe paper --minutes 15              # the paper's own recipe
    python benchmarks/solve.py --set anneal_lr=false --set lr=3e-4      # any learning option (bitcomm train --help)
"""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from bitcomm.learn.recipes import DEFAULT_RECIPE
from set_flag import add_set_flag, parse_set  # benchmarks/ is not a package: the script's folder is on the path

RUNGS = (("2x", 2.0), ("1.5x", 1.5), ("1.15x", 1.15))
GREEDY_RUNG = ("greedy 1.05x", 1.05)
EVAL_SEED = 12345
MAX_EPISODES = 10**9
"""No episode budget: the wall-clock budget (`--minutes`) ends a seed."""


def _last_row(run: Path) -> dict[str, str]:
    with (run / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows[-1]


def solve_seed(args: dict[str, Any], seed: int) -> dict[str, Any]:
    """Train one seed chunk by chunk until the last rung is confirmed or the budget is spent."""
    import torch

    from bitcomm.checkpoint import Diverged
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.learn.config import make_train_config
    from bitcomm.learn.run import train
    from bitcomm.learn.run_folder import has_checkpoint
    from bitcomm.policies.evaluation import evaluate, evaluate_checkpoint
    from bitcomm.policies.reference import OraclePolicy

    torch.set_num_threads(args["threads"])
    task = TaskConfig(EnvConfig(size=args["size"]), ChannelConfig(bits=args["bits"]))
    run = Path(args["out"]) / f"seed{seed}"
    overrides = dict(args["set"])
    cfg = make_train_config(
        args["recipe"],
        task,
        estimator=args["estimator"],
        messages=args["messages"],
        seed=seed,
        checkpoint_seconds=1e9,
        **overrides,
    )
    # the rungs are multiples of the oracle on the episodes that confirm them (not on the training seed's, which
    # config.json records: 8.74 / 8.95 / 8.80 steps for seeds 0-2 of the paper's task against 8.74 on these)
    oracle = evaluate(OraclePolicy(cfg.task), cfg.task, args["eval_episodes"], EVAL_SEED).mean_episode_length
    reached: dict[str, dict[str, float] | None] = {name: None for name, _ in (*RUNGS, GREEDY_RUNG)}
    checks: list[dict[str, float]] = []
    episodes, wall, rolling, resume = 0, 0.0, float("nan"), False
    diverged: str | None = None  # a run whose weights became NaN stops there; its last checkpoint is measured
    evaluated: dict[tuple[int, bool], float] = {}

    def play(greedy: bool) -> float:
        """Mean episode length of the latest checkpoint on the fixed episodes, evaluated once per checkpoint."""
        if not has_checkpoint(run):  # diverged before its first checkpoint
            return float("nan")
        if (episodes, greedy) not in evaluated:
            result = evaluate_checkpoint(run, args["eval_episodes"], EVAL_SEED, greedy=greedy)
            evaluated[episodes, greedy] = result.mean_episode_length
        return evaluated[episodes, greedy]

    while wall < args["minutes"] * 60 and episodes < args["max_episodes"]:
        target = episodes + args["chunk"]
        try:
            train(_with_budget(cfg, target), run, resume=resume, progress=False)
        except Diverged as err:
            diverged = str(err)
            print(f"seed {seed}: {diverged}", flush=True)
        resume = True
        row = _last_row(run)
        episodes, wall = int(row["episodes"]), float(row["wall_s"])
        rolling = float(row["charts/episode_length_rolling"])
        pending = [(name, k) for name, k in RUNGS if reached[name] is None]
        if pending and episodes >= 1000 and rolling < pending[0][1] * oracle:
            sampled = play(greedy=False)
            checks.append({"episodes": episodes, "rolling": rolling, "eval": sampled})
            for name, k in pending:
                if sampled < k * oracle:
                    reached[name] = {"episodes": episodes, "wall_s": round(wall, 1), "eval": round(sampled, 3)}
        if reached[RUNGS[-1][0]] is not None:
            greedy = play(greedy=True)
            checks.append({"episodes": episodes, "rolling": rolling, "greedy_eval": greedy})
            if greedy < GREEDY_RUNG[1] * oracle:
                reached[GREEDY_RUNG[0]] = {"episodes": episodes, "wall_s": round(wall, 1), "eval": round(greedy, 3)}
                break
        if diverged is not None:
            break
    final = {"sampled": play(greedy=False), "greedy": play(greedy=True)}
    return {
        "seed": seed,
        "oracle": oracle,
        "episodes": episodes,
        "wall_s": round(wall, 1),
        "reached": reached,
        "final_eval": {k: round(v, 3) for k, v in final.items()},
        "final_rolling": round(rolling, 3),
        "checks": checks,
        "diverged": diverged,
        "run": str(run),
    }


def over_seeds(results: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per rung: the median and the worst seed's training seconds and episodes (a seed that never reached
    the rung is the worst, as None), with how many seeds reached it; and the final evaluations' median."""
    import statistics

    out: dict[str, dict[str, Any]] = {}
    for name in (*(n for n, _ in RUNGS), GREEDY_RUNG[0]):
        hits = [r["reached"][name] for r in results]
        done = [h for h in hits if h is not None]
        missing = len(hits) - len(done)
        figures: dict[str, Any] = {"reached": f"{len(done)}/{len(hits)}"}
        for key in ("wall_s", "episodes"):
            values = sorted(h[key] for h in done) + [float("inf")] * missing
            median = statistics.median(values)
            figures[f"median_{key}"] = None if median == float("inf") else median
            figures[f"worst_{key}"] = None if missing else values[-1]
        out[name] = figures
    for kind in ("sampled", "greedy"):
        out[f"final {kind}"] = {"median": statistics.median(r["final_eval"][kind] for r in results)}
    return out


def _with_budget(cfg: Any, episodes: int) -> Any:
    from dataclasses import replace

    return replace(cfg, episodes=episodes)


def add_seed_flags(ap: argparse.ArgumentParser, run: str = "seed") -> None:
    """What a seed-by-seed benchmark trains (the recipe, the technique, the task and the seeds), and how many of its
    `run`s train at once, on how many torch threads each."""
    ap.add_argument("--recipe", default=DEFAULT_RECIPE)
    ap.add_argument("--estimator", default="improved")
    ap.add_argument("--messages", default="bitwise")
    ap.add_argument("--size", type=int, default=10)
    ap.add_argument("--bits", type=int, default=None, help="default: the task's default for the size")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2, help=f"{run}s trained at once")
    ap.add_argument("--threads", type=int, default=1, help=f"torch threads per {run}")


def check_seed_flags(a: argparse.Namespace, *positive: str) -> None:
    """`add_seed_flags`' values, `--jobs`, `--threads` and the `positive` flags checked (one line each, raised as
    ConfigError); `--bits` left out becomes the task's default for the grid's size."""
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.errors import check_int

    for name in ("seeds", "jobs", "threads", *positive):
        check_int(name, getattr(a, name), 1)
    check_int("first_seed", a.first_seed, 0)
    if a.bits is None:
        a.bits = TaskConfig(EnvConfig(size=a.size), ChannelConfig()).channel.bits


def seed_range(a: argparse.Namespace) -> range:
    """The seeds `add_seed_flags` asked for: `--seeds` of them from `--first-seed`."""
    return range(a.first_seed, a.first_seed + a.seeds)


def _solve_star(item: tuple[dict[str, Any], int]) -> dict[str, Any]:
    return solve_seed(*item)


def main() -> None:
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.errors import ConfigError, check_number
    from bitcomm.learn.config import make_train_config

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_seed_flags(ap)
    ap.add_argument("--minutes", type=float, default=15.0, help="training wall-time budget per seed")
    ap.add_argument(
        "--max-episodes",
        type=int,
        default=MAX_EPISODES,
        help="episode budget per seed, played in whole --chunk's: training stops at the first chunk that reaches it, "
        "which may pass it (and, where the recipe anneals, the horizon of the learning-rate schedule)",
    )
    ap.add_argument("--chunk", type=int, default=1024, help="episodes between checks")
    ap.add_argument("--eval-episodes", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=None, help="default runs/solve/<recipe>-<size>x<size>-<time>")
    add_set_flag(ap)
    a = ap.parse_args()
    try:  # bad input is one line before any seed starts
        overrides = parse_set(ap, a.set)
        check_seed_flags(a, "chunk", "eval_episodes", "max_episodes")
        check_number("minutes", a.minutes, 0.0, strict=True)
        task = TaskConfig(EnvConfig(size=a.size), ChannelConfig(bits=a.bits))
        cfg = make_train_config(a.recipe, task, estimator=a.estimator, messages=a.messages, **dict(overrides))
        if cfg.anneals and not cfg.anneal_episodes:
            if a.max_episodes == MAX_EPISODES:
                ap.error(
                    f"recipe {a.recipe} anneals over the budget: give --max-episodes N (the episodes its schedules "
                    "span, e.g. 200000 on 10x10), or --set anneal_lr=false"
                )
            overrides.append(("anneal_episodes", a.max_episodes))  # one schedule across the chunks
    except ConfigError as err:
        ap.error(str(err))
    out = a.out or Path("runs/solve") / f"{a.recipe}-{a.size}x{a.size}-{time.strftime('%Y%m%d-%H%M%S')}"
    args = {**vars(a), "out": str(out), "set": overrides}
    seeds = seed_range(a)
    print(
        f"solve: recipe {a.recipe}, {a.estimator} + {a.messages}, {a.size}x{a.size}, {a.bits} bits, "
        f"options {dict(overrides)}, seeds {list(seeds)}, {a.minutes} min each, out {out}",
        flush=True,
    )
    results = []
    # not a multiprocessing.Pool: its workers are daemonic and cannot start a3c's worker processes
    with ProcessPoolExecutor(min(a.jobs, a.seeds), mp_context=mp.get_context("spawn")) as pool:
        for r in pool.map(_solve_star, [(args, s) for s in seeds]):
            rungs = "  ".join(
                f"{name}: " + (f"{v['episodes']} ep / {v['wall_s']} s" if v else "not reached")
                for name, v in r["reached"].items()
            )
            print(
                f"seed {r['seed']}: {rungs}  | after {r['episodes']} ep / {r['wall_s']} s: "
                f"sampled {r['final_eval']['sampled']}, greedy {r['final_eval']['greedy']} "
                f"(oracle {r['oracle']:.2f})",
                flush=True,
            )
            results.append(r)
    summary = {
        "recipe": a.recipe,
        "estimator": a.estimator,
        "messages": a.messages,
        "size": a.size,
        "bits": a.bits,
        "options": dict(overrides),
        "minutes": a.minutes,
        "threads": a.threads,
        "jobs": a.jobs,
        "seeds": [{k: v for k, v in r.items() if k != "checks"} for r in results],
        "over_seeds": over_seeds(results),
    }
    for name, figures in summary["over_seeds"].items():
        print(f"{name}: " + ", ".join(f"{k} {v}" for k, v in figures.items()), flush=True)
    (out / "summary.json").write_text(json.dumps({**summary, "checks": [r["checks"] for r in results]}, indent=1))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
