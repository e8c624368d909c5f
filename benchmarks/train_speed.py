"""Training throughput: agent-steps per second, learning included, for each mode and recipe.

Runs the real trainer (`bitcomm.learn.run.train`) on the default task with the default networks
into a temporary folder, and reads `metrics.csv`: throughput is measured over the batches after the
warm-up ones (agent-steps played / wall seconds between those rows). torch uses `--threads` (2) threads in
sync mode; in a3c mode each of the W workers uses 1. On a machine where another process keeps a core
busy, 2 threads can be many times slower than 1 (the threads wait on each other): compare both.
The last line printed is one JSON object.

`passes` is how many forward and backward passes each agent-step goes through (the recipe's
`epochs`): `reinforced` reuses each batch for 4 epochs of 4 minibatch steps. `--single-pass` also times
each multi-pass recipe with `epochs=1, minibatches=1` (one gradient step per batch, the plain batched
actor-critic), so the trainer's own cost and the recipe's reuse can be told apart in one run.
`--num-envs N` sets every recipe's episodes per batch: `--recipes paper --num-envs 64` is the paper's
network and update over the batches `reinforced` uses. `--size`, `--bits` and `--messages` time another
task or message head (`--size 32 --bits 10 --messages onehot`: a one-hot head of 1,024 outputs); `--set
NAME=VALUE` any other learning option (`--set sender_hidden=64`: a narrower message head of its own).

    python benchmarks/train_speed.py [--modes sync,a3c] [--recipes paper,reinforced] [--batches 3] [--single-pass]
        [--num-envs N] [--size S] [--bits K] [--messages bitwise|onehot] [--set NAME=VALUE ...]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError, check_int
from bitcomm.learn.config import RECIPES, make_train_config
from bitcomm.learn.run import train
from set_flag import add_set_flag, parse_set  # benchmarks/ is not a package: the script's folder is on the path


def measure(
    mode: str,
    recipe: str,
    batches: int,
    warmup: int,
    workers: int,
    single_pass: bool = False,
    num_envs: int | None = None,
    task: TaskConfig | None = None,
    messages: str | None = None,
    overrides: dict[str, Any] | None = None,
) -> dict[str, float]:
    num_envs = RECIPES[recipe]["num_envs"] if num_envs is None else num_envs
    reuse = dict(epochs=1, minibatches=1) if single_pass else {}
    w = workers if mode == "a3c" else 1
    if num_envs == 1:  # one-episode batches are short: time more of them
        batches, warmup = batches * 10, warmup * 5
    episodes = (batches + warmup) * w * num_envs
    cfg = make_train_config(
        recipe,
        task or TaskConfig(),
        mode=mode,
        messages=messages,
        workers=workers,
        num_envs=num_envs,
        episodes=episodes,
        checkpoint_seconds=1e9,
        **{**(overrides or {}), **reuse},
    )
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
        "passes": cfg.epochs,
        "gradient_steps_per_batch": cfg.epochs * cfg.minibatches,
        "workers": w,
        "total_s": round(total, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modes", default="sync,a3c")
    ap.add_argument("--recipes", default="reinforced,paper")
    ap.add_argument("--batches", type=int, default=3, help="timed batches per worker (x10 for one-episode batches)")
    ap.add_argument("--warmup", type=int, default=1, help="untimed batches per worker (x5 for one-episode batches)")
    ap.add_argument("--workers", type=int, default=2, help="a3c workers")
    ap.add_argument("--threads", type=int, default=2, help="torch threads in sync mode (default %(default)s)")
    ap.add_argument(
        "--single-pass", action="store_true", help="also time each multi-pass recipe with epochs=1, minibatches=1"
    )
    ap.add_argument("--num-envs", type=int, default=None, help="episodes per batch (default: each recipe's)")
    ap.add_argument("--size", type=int, default=EnvConfig.size, help="grid size (default %(default)s)")
    ap.add_argument("--bits", type=int, default=ChannelConfig.bits, help="message bits K (default %(default)s)")
    ap.add_argument("--messages", default=None, help="message head, bitwise or onehot (default: each recipe's)")
    add_set_flag(ap)
    args = ap.parse_args()
    recipes, modes = args.recipes.split(","), args.modes.split(",")
    try:  # bad input is one line before anything runs
        overrides = dict(parse_set(ap, args.set))
        own = {"mode": "give --modes", "workers": "give --workers", "num_envs": "give --num-envs",
               "messages": "give --messages", "checkpoint_seconds": "a timed run never checkpoints"}  # fmt: skip
        for name in sorted(own.keys() & overrides.keys()):  # options this script sets itself
            ap.error(f"--set {name}=...: {own[name]}")
        task = TaskConfig(env=EnvConfig(size=args.size), channel=ChannelConfig(bits=args.bits))
        for recipe in recipes:
            for mode in modes:
                make_train_config(
                    recipe,
                    task,
                    mode=mode,
                    workers=args.workers,
                    num_envs=args.num_envs,
                    messages=args.messages,
                    **overrides,
                )
        for name in ("threads", "batches", "warmup"):  # timing starts after the last warm-up batch
            check_int(name, getattr(args, name), 1)
    except ConfigError as err:
        ap.error(str(err))
    torch.set_num_threads(args.threads)
    results = {}
    for recipe in recipes:
        multi_pass = RECIPES[recipe]["epochs"] * RECIPES[recipe]["minibatches"] > 1
        for single_pass in (False, True) if args.single_pass and multi_pass else (False,):
            for mode in modes:
                r = measure(
                    mode,
                    recipe,
                    args.batches,
                    args.warmup,
                    args.workers,
                    single_pass,
                    args.num_envs,
                    task,
                    args.messages,
                    overrides,
                )
                name = f"{mode}/{recipe}" + ("/single-pass" if single_pass else "")
                results[name] = r
                print(
                    f"{name:22s} workers={r['workers']} num_envs={r['num_envs']:4d} passes={r['passes']}: "
                    f"{r['agent_steps_per_s']:>10,.0f} agent-steps/s ({r['agent_steps']} steps in {r['wall_s']} s)",
                    flush=True,
                )
    task_name = f"{args.size}x{args.size}, K={args.bits}" + (f", {args.messages}" if args.messages else "")
    summary = {"benchmark": "train_speed", "task": task_name, "torch_threads": args.threads, "results": results}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
