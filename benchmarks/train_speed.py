"""Training throughput: agent-steps per second, learning included, for each mode and recipe.

Runs the real trainer (`bitcomm.train.run.train`) on the default task with the default networks
into a temporary folder, and reads `metrics.csv`: throughput is measured over the batches after the
warm-up ones (agent-steps played / wall seconds between those rows). torch uses `--threads` (2) threads in
sync mode; in a3c mode each of the W workers uses 1. On a machine where another process keeps a core
busy, 2 threads can be many times slower than 1 (the threads wait on each other): compare both.
The last line printed is one JSON object.

    python benchmarks/train_speed.py [--modes sync,a3c] [--recipes paper,fast] [--batches 3]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path

import torch

from bitcomm.config import TaskConfig
from bitcomm.train.config import RECIPES, make_train_config
from bitcomm.train.run import train


def measure(mode: str, recipe: str, batches: int, warmup: int, workers: int) -> dict[str, float]:
    num_envs = RECIPES[recipe]["num_envs"]
    w = workers if mode == "a3c" else 1
    if num_envs == 1:  # one-episode batches are short: time more of them
        batches, warmup = batches * 10, warmup * 5
    episodes = (batches + warmup) * w * num_envs
    cfg = make_train_config(recipe, TaskConfig(), mode=mode, workers=workers, episodes=episodes, checkpoint_seconds=1e9)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        train(cfg, Path(tmp) / "run", progress=False)
        total = time.perf_counter() - t0
        with (Path(tmp) / "run" / "metrics.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
    first, last = rows[warmup * w - 1], rows[-1]
    steps = int(last["agent_steps"]) - int(first["agent_steps"])
    wall = float(last["wall_s"]) - float(first["wall_s"])
    return {
        "agent_steps_per_s": round(steps / wall, 1),
        "agent_steps": steps,
        "wall_s": round(wall, 2),
        "batches": len(rows) - warmup * w,
        "num_envs": num_envs,
        "workers": w,
        "total_s": round(total, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modes", default="sync,a3c")
    ap.add_argument("--recipes", default="fast,paper")
    ap.add_argument("--batches", type=int, default=3, help="timed batches per worker (x10 for one-episode batches)")
    ap.add_argument("--warmup", type=int, default=1, help="untimed batches per worker (x5 for one-episode batches)")
    ap.add_argument("--workers", type=int, default=2, help="a3c workers")
    ap.add_argument("--threads", type=int, default=2, help="torch threads in sync mode (default %(default)s)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    results = {}
    for recipe in args.recipes.split(","):
        for mode in args.modes.split(","):
            r = measure(mode, recipe, args.batches, args.warmup, args.workers)
            results[f"{mode}/{recipe}"] = r
            print(
                f"{mode:5s} {recipe:6s} workers={r['workers']} num_envs={r['num_envs']:4d}: "
                f"{r['agent_steps_per_s']:>10,.0f} agent-steps/s ({r['agent_steps']} steps in {r['wall_s']} s)",
                flush=True,
            )
    summary = {"benchmark": "train_speed", "task": "default", "torch_threads": args.threads, "results": results}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
