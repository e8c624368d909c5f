"""Training on Ray against the local trainers (issue 19): agent-steps per second and time to 2x the oracle.

Trains one recipe (default `reinforced`; `--single-pass`: one gradient step per batch) on a small task
(default 4x4, 4 bits) with the local sync trainer, the local a3c trainer (`--a3c-workers`), and on Ray with
1, 2 and 4 rollout actors, synchronous (staleness 0) and asynchronous (staleness = actors), `--repeats` seeds
each, on one local Ray instance started here with a CPU per actor. Every run plays `--episodes` episodes into
a temporary folder (the real trainer, checkpoints only at the end) and is read back from metrics.csv:

    agent_steps_per_s   agent-steps / wall seconds from the second logged update to the last (start-up of
                        processes and actors excluded)
    time_to_2x_s        wall seconds (start-up included) until the rolling mean episode length (last 1,000
                        episodes) is below twice the oracle's; episodes_to_2x likewise
    update_s            median learner update (Ray runs); collect_s: median seconds an actor takes per batch
    actor_steps_per_s   agent-steps of one batch / collect_s: what one actor supplies

Medians over the repeats are printed as a table and written as JSON (`--json`, and the last line printed).
From the 1-actor synchronous run (actor and learner take turns, neither waits on the other's core) the
learner's update time and one actor's collection time give `actors_to_saturate` = collect_s / update_s +
1: the number of asynchronous actors whose batches arrive as fast as the single learner consumes them (an
actor starts its next batch once the learner has updated on its last, so its cycle is collect_s + update_s).

    python benchmarks/ray_scaling.py [--size 4] [--bits 4] [--episodes 4096] [--repeats 2] [--actors 1,2,4]
        [--single-pass]

`--stale-check` instead trains the recipe's learner in this process, without Ray, for `--stale-updates`
updates on batches played with the current weights, with the weights one update old, and one update old
without PPO clipping, and prints the mean episode length of every 8 updates: what staleness alone does.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError, check_int
from bitcomm.learn.config import make_train_config
from bitcomm.learn.run import train

SKIP = 2
"""Rows (updates) before throughput is timed: the first ones pay for starting processes and actors."""


def read(run: Path) -> tuple[list[dict[str, str]], float | None]:
    with (run / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows, json.loads((run / "config.json").read_text()).get("oracle_mean_episode_length")


def measure(name: str, seed: int, args: argparse.Namespace, **options: Any) -> dict[str, Any]:
    task = TaskConfig(EnvConfig(size=args.size), ChannelConfig(bits=args.bits))
    cfg = make_train_config(args.recipe, task, seed=seed, episodes=args.episodes, checkpoint_seconds=1e9, **options)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        train(cfg, Path(tmp) / "run", progress=False)
        total = time.perf_counter() - t0
        rows, oracle = read(Path(tmp) / "run")
    first, last = rows[min(SKIP, len(rows) - 1) - 1], rows[-1]
    steps = int(last["agent_steps"]) - int(first["agent_steps"])
    reached = [r for r in rows if oracle is not None and float(r["charts/episode_length_rolling"]) < 2 * oracle]
    out: dict[str, Any] = {
        "agent_steps_per_s": steps / max(float(last["wall_s"]) - float(first["wall_s"]), 1e-9),
        "time_to_2x_s": float(reached[0]["wall_s"]) if reached else None,
        "episodes_to_2x": int(reached[0]["episodes"]) if reached else None,
        "final_rolling_length": float(last["charts/episode_length_rolling"]),
        "oracle": oracle,
        "total_s": total,
    }
    if "ray/update_s" in rows[0]:
        timed = rows[SKIP:] or rows
        out["update_s"] = statistics.median(float(r["ray/update_s"]) for r in timed)
        out["collect_s"] = statistics.median(float(r["ray/collect_s"]) for r in timed)
        batches = max(int(last["batch"]) - int(first["batch"]), 1)
        per_batch = (int(last["agent_steps"]) - int(first["agent_steps"])) / batches if steps else 0.0
        out["actor_steps_per_s"] = per_batch / out["collect_s"]
        out["dropped"] = int(last["ray/dropped"])
    print(f"  {name} seed {seed}: {json.dumps({k: v for k, v in out.items() if v is not None})}", flush=True)
    return out


def stale_check(args: argparse.Namespace) -> dict[str, list[float]]:
    """Mean training episode length per 8 updates when every batch is played with weights `stale` updates old."""
    import copy

    import numpy as np

    from bitcomm.learn.learner import Learner
    from bitcomm.learn.rollout import Collector

    task = TaskConfig(EnvConfig(size=args.size), ChannelConfig(bits=args.bits))
    out = {}
    for name, stale, options in (("fresh", 0, {}), ("1 update old", 1, {}), ("1 update old, clip 0", 1, {"clip": 0.0})):
        cfg = make_train_config(args.recipe, task, **options)
        torch.manual_seed(0)
        learner, generator = Learner(cfg), torch.Generator().manual_seed(0)
        collector = Collector(cfg.training_task, cfg.num_envs)
        history, lengths = [copy.deepcopy(learner.policy)], []
        for k in range(args.stale_updates):
            behaviour = history[max(0, len(history) - 1 - stale)]
            ro = collector.collect(behaviour, np.random.SeedSequence(0, spawn_key=(k,)), generator)
            lengths.append(float(ro.length.mean()))
            learner.update(ro, generator)
            history = [*history[-1:], copy.deepcopy(learner.policy)]
        out[name] = [round(float(np.mean(lengths[i : i + 8])), 2) for i in range(0, len(lengths), 8)]
        print(f"  {name:22s} mean length per 8 updates: {out[name]}", flush=True)
    return out


def median(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Each figure's median over the repeats (None if a repeat lacks it: a 2x never reached)."""
    keys = results[0].keys()
    return {
        k: None if any(r[k] is None for r in results) else round(statistics.median(r[k] for r in results), 4)
        for k in keys
    }


def fmt(value: Any, spec: str) -> str:
    """`value` formatted by `spec` (`>15.1f`), or a dash as wide."""
    return format(value, spec) if value is not None else format("-", ">" + spec[1:].split(".")[0].rstrip(",f"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=4)
    ap.add_argument("--bits", type=int, default=4)
    ap.add_argument("--recipe", default="reinforced")
    ap.add_argument("--episodes", type=int, default=4096, help="episodes per run (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=2, help="seeds per configuration (default %(default)s)")
    ap.add_argument("--actors", default="1,2,4", help="Ray actor counts (default %(default)s)")
    ap.add_argument("--a3c-workers", type=int, default=2, help="a3c worker processes, 0: skip a3c (default 2)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the learner (default %(default)s)")
    ap.add_argument(
        "--single-pass",
        action="store_true",
        help="one gradient step per batch (epochs=1, minibatches=1): a cheap learner",
    )
    ap.add_argument("--stale-check", action="store_true", help="only train without Ray on stale batches (above)")
    ap.add_argument("--stale-updates", type=int, default=48, help="updates of --stale-check (default %(default)s)")
    ap.add_argument("--json", type=Path, default=None, help="also write the summary here")
    args = ap.parse_args()
    try:  # bad input is one line before anything runs
        actors = [int(a) for a in args.actors.split(",")]
        for name in ("size", "bits", "episodes", "repeats", "threads"):
            check_int(name, getattr(args, name), 1)
        for n in actors:
            check_int("actors", n, 1)
        check_int("a3c_workers", args.a3c_workers, 0)
        make_train_config(args.recipe, TaskConfig(EnvConfig(size=args.size), ChannelConfig(bits=args.bits)))
    except (ConfigError, ValueError) as err:
        ap.error(str(err))
    torch.set_num_threads(args.threads)
    if args.stale_check:
        summary = {"benchmark": "ray_scaling/stale_check", "recipe": args.recipe, "lengths": stale_check(args)}
        print(json.dumps(summary))
        return
    import ray

    ray.init(num_cpus=max(actors), include_dashboard=False, log_to_driver=False, configure_logging=False)
    base: dict[str, Any] = {"epochs": 1, "minibatches": 1} if args.single_pass else {}
    plans: list[tuple[str, dict[str, Any]]] = [("local sync", {})]
    if args.a3c_workers:
        plans.append((f"local a3c x{args.a3c_workers}", {"mode": "a3c", "workers": args.a3c_workers}))
    for n in actors:
        plans.append((f"ray sync x{n}", {"backend": "ray", "workers": n}))
    for n in actors:
        plans.append((f"ray async x{n} (S={n})", {"backend": "ray", "workers": n, "staleness": n}))
    t0 = time.perf_counter()
    results = {}
    for name, options in plans:
        results[name] = {
            **median([measure(name, seed, args, **base, **options) for seed in range(args.repeats)]),
            **options,
        }
    ray.shutdown()
    print(
        f"\n{args.size}x{args.size}, {args.bits} bits, recipe {args.recipe}{' (single pass)' * args.single_pass}, "
        f"{args.episodes} episodes a run, "
        f"medians of {args.repeats} seeds, {os.cpu_count()} CPU cores, learner threads {args.threads}"
    )
    print(f"{'trainer':22s} {'agent-steps/s':>14s} {'time to 2x (s)':>15s} {'episodes to 2x':>15s} "
          f"{'update (s)':>11s} {'collect (s)':>12s} {'actor steps/s':>14s}")  # fmt: skip
    for name, r in results.items():
        print(
            f"{name:22s} {r['agent_steps_per_s']:>14,.0f} {fmt(r['time_to_2x_s'], '>15.1f')} "
            f"{fmt(r['episodes_to_2x'], '>15.0f')} {fmt(r.get('update_s'), '>11.3f')} "
            f"{fmt(r.get('collect_s'), '>12.3f')} {fmt(r.get('actor_steps_per_s'), '>14,.0f')}"
        )
    one = results.get("ray sync x1")
    summary: dict[str, Any] = {
        "benchmark": "ray_scaling",
        "task": {"size": args.size, "bits": args.bits},
        "recipe": args.recipe,
        "single_pass": args.single_pass,
        "episodes": args.episodes,
        "repeats": args.repeats,
        "cpu_cores": os.cpu_count(),
        "learner_threads": args.threads,
        "total_s": round(time.perf_counter() - t0, 1),
        "results": results,
    }
    if one is not None:
        summary["actors_to_saturate"] = round(one["collect_s"] / one["update_s"] + 1, 2)
        print(
            f"one learner update {one['update_s']:.3f} s, one actor's batch {one['collect_s']:.3f} s: "
            f"about {summary['actors_to_saturate']:.1f} asynchronous actors keep the learner busy"
        )
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
