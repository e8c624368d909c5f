"""How many seeds play greedily within 1.05x the oracle at the end of training, and does keeping the checkpoint
that plays a held-out set best (`--held-out-every`) lift greedy play?

Trains S seeds of a recipe (improved + bitwise under the default unless told otherwise), then plays each run's
latest checkpoint greedily and sampled, and its best by the held-out set (`checkpoints/best.json`) greedily, on
`--eval-episodes` episodes of seed 12345, a set that neither training nor the held-out evaluation plays, and reports
per seed and over seeds their mean episode length against 1.05x the oracle's on the same episodes (issue 16's
greedy target). `--held-out-every 0` trains with no held-out evaluation (the default recipe's runs, as `bitcomm
train` makes them) and measures the latest checkpoint only. A seed already measured in `--out` (`seed<N>.json`) is
kept and an unfinished run resumes, so a study stopped part way goes on where it stopped. The last line printed is
one JSON object.

    python benchmarks/greedy_selection.py --seeds 28 --jobs 2 --held-out-every 0 --eval-episodes 2000 \\
        --out runs/greedy-seeds                                   # the README's count of seeds within 1.05x
    python benchmarks/greedy_selection.py --seeds 28 --jobs 2 --held-out-every 0 --eval-episodes 2000 \\
        --set message_logit_decay=0 --out runs/greedy-seeds-no-decay  # any learning option (bitcomm train --help)
    python benchmarks/greedy_selection.py --seeds 16 --jobs 2 --episodes 200000 --held-out-every 8192 \\
        --eval-episodes 10000 --out runs/greedy-selection
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import statistics
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from set_flag import add_set_flag, parse_set  # benchmarks/ is not a package: the script's folder is on the path
from solve import (  # benchmarks/ is not a package: run as a script, it is on sys.path
    add_seed_flags,
    check_seed_flags,
    seed_range,
)

EVAL_SEED = 12345
TARGET = 1.05
"""Greedy play within this multiple of the oracle (issue 16)."""


def _config(args: dict[str, Any], seed: int) -> Any:
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.learn.config import make_train_config

    task = TaskConfig(EnvConfig(size=args["size"]), ChannelConfig(bits=args["bits"]))
    return make_train_config(
        args["recipe"],
        task,
        estimator=args["estimator"],
        messages=args["messages"],
        seed=seed,
        episodes=args["episodes"],
        held_out_every=args["held_out_every"],
        held_out_episodes=args["held_out_episodes"] if args["held_out_every"] else None,  # read only with a set
        train_max_steps=args.get("train_max_steps"),  # None: the recipe's cut
        keep_checkpoints=1,
        **dict(args.get("set", ())),
    )


def measured(args: dict[str, Any]) -> tuple[str, ...]:
    """The checkpoints a seed is measured at: the best by the held-out set only where there is one."""
    return ("latest", "best") if args["held_out_every"] else ("latest",)


def measure_seed(args: dict[str, Any], seed: int) -> dict[str, Any]:
    """Train one seed (or resume it), then play its checkpoints greedily, and the latest sampled too, on the test
    set."""
    import torch

    from bitcomm.learn.run import train
    from bitcomm.learn.run_folder import has_checkpoint
    from bitcomm.policies.evaluation import evaluate_checkpoint

    out = Path(args["out"])
    eval_seed = args.get("eval_seed", EVAL_SEED)
    result_file = out / f"seed{seed}.json"
    if result_file.is_file():
        return dict(json.loads(result_file.read_text()), kept=True)
    torch.set_num_threads(args["threads"])
    run = out / f"seed{seed}"
    train(_config(args, seed), run, resume=has_checkpoint(run), progress=False)
    result: dict[str, Any] = {"seed": seed, "run": str(run)}
    for which in measured(args):
        pointer = run / "checkpoints" / f"{which}.json"
        played = evaluate_checkpoint(pointer, args["eval_episodes"], eval_seed, greedy=True)
        result[which] = {
            "episodes": json.loads(pointer.read_text())["episodes"],
            "greedy": round(played.mean_episode_length, 4),
            "stalled": round(1.0 - played.success_rate, 5),
        }
    sampled = evaluate_checkpoint(run / "checkpoints" / "latest.json", args["eval_episodes"], eval_seed)
    result["latest"]["sampled"] = round(sampled.mean_episode_length, 4)
    result["latest"]["sampled_stalled"] = round(1.0 - sampled.success_rate, 5)
    tmp = result_file.with_suffix(".tmp")
    tmp.write_text(json.dumps(result) + "\n")
    tmp.replace(result_file)
    return result


def over_seeds(results: list[dict[str, Any]], threshold: float) -> dict[str, Any]:
    """How many seeds each checkpoint brings within the target, the median greedy length (and the latest's
    sampled), and how the best compares with the latest seed by seed where there is a best."""
    summary: dict[str, Any] = {}
    for which in ("latest", "best"):
        if not all(which in r for r in results):
            continue
        greedy = [r[which]["greedy"] for r in results]
        summary[which] = {
            "within": f"{sum(g <= threshold for g in greedy)}/{len(greedy)}",
            "median_greedy": statistics.median(greedy),
        }
    sampled = [r["latest"]["sampled"] for r in results if "sampled" in r["latest"]]
    if sampled:
        summary["latest"]["median_sampled"] = statistics.median(sampled)
    if "best" not in summary:
        return summary
    pairs = [(r["best"]["greedy"], r["latest"]["greedy"]) for r in results]
    summary["best_against_latest"] = {
        "better": sum(b < la for b, la in pairs),
        "same": sum(b == la for b, la in pairs),
        "worse": sum(b > la for b, la in pairs),
    }
    return summary


def main() -> None:
    from bitcomm.errors import ConfigError, check_int
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.reference import OraclePolicy

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_seed_flags(ap)
    ap.add_argument("--episodes", type=int, default=200_000, help="training budget per seed")
    ap.add_argument("--held-out-every", type=int, default=8192, help="0: no held-out set; the latest only")
    ap.add_argument("--held-out-episodes", type=int, default=1000)
    ap.add_argument("--eval-episodes", type=int, default=10_000, help="test episodes (seed 12345) per checkpoint")
    ap.add_argument("--out", type=Path, default=Path("runs/greedy-selection"))
    add_set_flag(ap)
    a = ap.parse_args()
    try:  # bad input is one line before any seed starts
        overrides = parse_set(ap, a.set)
        check_seed_flags(a, "eval_episodes", "episodes")
        check_int("held_out_every", a.held_out_every, 0)
        args = {**vars(a), "out": str(a.out), "set": overrides}
        task = _config(args, a.first_seed).task
        oracle = evaluate(OraclePolicy(task), task, a.eval_episodes, EVAL_SEED).mean_episode_length
    except ConfigError as err:
        ap.error(str(err))
    a.out.mkdir(parents=True, exist_ok=True)
    threshold = TARGET * oracle
    seeds = seed_range(a)
    print(
        f"greedy selection: {a.recipe}, {a.estimator} + {a.messages}, {a.size}x{a.size}, {a.bits} bits, "
        f"{a.episodes} episodes, held out every {a.held_out_every} ({a.held_out_episodes} episodes), seeds "
        f"{list(seeds)}; oracle {oracle:.3f} on {a.eval_episodes} episodes of seed {EVAL_SEED}, "
        f"target {threshold:.3f}; out {a.out}",
        flush=True,
    )
    results = []
    with ProcessPoolExecutor(min(a.jobs, a.seeds), mp_context=mp.get_context("spawn")) as pool:
        for r in pool.map(measure_seed, [args] * len(seeds), seeds):
            print(
                f"seed {r['seed']}{' (kept)' if r.get('kept') else ''}: "
                + "  ".join(
                    f"{w} ({r[w]['episodes']} ep): greedy {r[w]['greedy']:.2f}, {100 * r[w]['stalled']:.2f}% stalled"
                    + (f", sampled {r[w]['sampled']:.2f}" if "sampled" in r[w] else "")
                    for w in measured(args)
                ),
                flush=True,
            )
            results.append(r)
    summary = over_seeds(results, threshold)
    for key, figures in summary.items():
        print(f"{key}: " + ", ".join(f"{k} {v}" for k, v in figures.items()), flush=True)
    print(json.dumps({**{k: v for k, v in args.items()}, "oracle": oracle, "target": threshold,
                      "seeds": results, "over_seeds": summary}))  # fmt: skip


if __name__ == "__main__":
    main()
