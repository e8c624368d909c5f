"""What keeping freed memory is worth (`bitcomm.learn.allocator`): a batch's collection and update, timed
in fresh processes with the setting on and with it off (`BITCOMM_KEEP_FREED_MEMORY=0`), taking turns.

malloc's settings hold for a whole process, so each measurement is its own process: it plays one batch of
the recipe with a fresh policy, makes one warm-up update, then times `--updates` collections and updates and
prints their medians. The parent alternates on/off for `--rounds` rounds, so both see the same machine,
and reports the medians over rounds, the ratio off/on and the minor page faults of each. The last line
printed is one JSON object.

    python benchmarks/allocator.py [--size 32] [--bits 10] [--messages onehot] [--rounds 3] [--updates 3]
        [--threads 1] [--num-envs N]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np


def measure(
    size: int, bits: int, messages: str | None, updates: int, threads: int, num_envs: int | None
) -> dict[str, float]:
    """Run in the child: medians of `updates` collections and updates of the recipe's batch, in seconds."""
    import torch

    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.learn.allocator import keep_freed_memory
    from bitcomm.learn.config import make_train_config
    from bitcomm.learn.learner import Learner
    from bitcomm.learn.rollout import Collector

    applied = keep_freed_memory()
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    task = TaskConfig(env=EnvConfig(size=size), channel=ChannelConfig(bits=bits))
    cfg = make_train_config("reinforced", task, messages=messages, num_envs=num_envs, mode="sync")
    learner, generator = Learner(cfg), torch.Generator().manual_seed(0)
    collector = Collector(cfg.training_task, cfg.num_envs)
    ro = collector.collect(learner.policy, np.random.SeedSequence(0), generator)
    learner.update(ro, generator)
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    collect_s, update_s = [], []
    for k in range(updates):
        t0 = time.perf_counter()
        collector.collect(learner.policy, np.random.SeedSequence(1 + k), generator)
        t1 = time.perf_counter()
        learner.update(ro, generator)
        collect_s.append(t1 - t0)
        update_s.append(time.perf_counter() - t1)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0
    return {
        "applied": applied,
        "collect_s": float(np.median(collect_s)),
        "update_s": float(np.median(update_s)),
        "minor_faults_per_batch": faults / updates,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=32, help="grid size (default %(default)s)")
    ap.add_argument("--bits", type=int, default=10, help="message bits K (default %(default)s)")
    ap.add_argument("--messages", default="onehot", help="message head, bitwise or onehot (default %(default)s)")
    ap.add_argument("--rounds", type=int, default=3, help="processes per setting, taking turns")
    ap.add_argument("--updates", type=int, default=3, help="timed batches per process")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--num-envs", type=int, default=None, help="episodes in the batch (default: the recipe's)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(measure(a.size, a.bits, a.messages, a.updates, a.threads, a.num_envs)))
        return
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.errors import ConfigError, check_int
    from bitcomm.learn.config import make_train_config

    try:  # bad input is one line before anything runs
        for name in ("rounds", "updates", "threads"):
            check_int(name, getattr(a, name), 1)
        task = TaskConfig(env=EnvConfig(size=a.size), channel=ChannelConfig(bits=a.bits))
        make_train_config("reinforced", task, messages=a.messages, num_envs=a.num_envs, mode="sync")
    except ConfigError as err:
        ap.error(str(err))
    child = [sys.executable, __file__, "--child", *sys.argv[1:]]
    runs: dict[str, list[dict[str, float]]] = {"on": [], "off": []}
    for r in range(a.rounds):
        for setting in ("on", "off"):
            env = {**os.environ, "BITCOMM_KEEP_FREED_MEMORY": "1" if setting == "on" else "0"}
            out = subprocess.run(child, env=env, check=True, capture_output=True, text=True).stdout
            runs[setting].append(json.loads(out.strip().splitlines()[-1]))
            m = runs[setting][-1]
            print(
                f"round {r + 1} {setting:3s}: collect {m['collect_s']:.3f} s, update {m['update_s']:.3f} s, "
                f"{m['minor_faults_per_batch']:,.0f} minor page faults per batch"
            )
    med = {s: {k: float(np.median([m[k] for m in ms])) for k in ms[0]} for s, ms in runs.items()}
    batch = {s: m["collect_s"] + m["update_s"] for s, m in med.items()}
    task_name = f"{a.size}x{a.size}, K={a.bits}, {a.messages}"
    print(
        f"{task_name}: update {med['off']['update_s']:.3f} s -> {med['on']['update_s']:.3f} s "
        f"({med['off']['update_s'] / med['on']['update_s']:.2f}x), batch {batch['off'] / batch['on']:.2f}x "
        f"(medians of {a.rounds} processes each, {a.threads} thread(s))"
    )
    summary = {
        "benchmark": "allocator",
        "task": task_name,
        "threads": a.threads,
        "applied": bool(runs["on"][0]["applied"]),
        "median": {s: {k: round(v, 4) for k, v in m.items() if k != "applied"} for s, m in med.items()},
        "update_speedup": round(med["off"]["update_s"] / med["on"]["update_s"], 3),
        "batch_speedup": round(batch["off"] / batch["on"], 3),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
