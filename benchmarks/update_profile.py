"""Where one learning update spends its time: `torch.profiler` over a few updates of one batch, grouped.

Plays one batch of the recipe (default: `reinforced`, the default task) with a fresh policy, warms up with
one update, then profiles `--updates` more on the same batch and prints the share of self CPU time of each
group of operators (matrix products, activations, indexing and copies, the optimizer, the rest) and the
slowest operators, and the operations of its matrix products (one more update profiled `with_flops`: per update,
per agent-step, and per second of their own time, to set against what a core can do); then, without the profiler,
one batch's milliseconds by part: playing it, the critic's side of its update and the policy's (`time_parts`). The
last line printed is one JSON object. It answers "what would a faster update have to remove":
`benchmarks/train_speed.py` measures the throughput itself.

`--size`, `--bits` and `--messages` profile another task or message head (`--size 32 --bits 10 --messages
onehot`: the 1,024-output head of the 32x32 study).

    python benchmarks/update_profile.py [--recipe reinforced] [--updates 3] [--threads 1] [--num-envs N]
        [--size S] [--bits K] [--messages bitwise|onehot]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from typing import Any

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError, check_int
from bitcomm.learn.allocator import keep_freed_memory
from bitcomm.learn.config import TrainConfig, make_train_config
from bitcomm.learn.learner import Learner
from bitcomm.learn.recipes import RECIPES
from bitcomm.learn.rollout import Collector

GROUPS: dict[str, tuple[str, ...]] = {
    "matrix products": ("aten::mm", "aten::addmm", "aten::bmm", "aten::matmul", "aten::convolution"),
    "activations": ("aten::threshold_backward", "aten::clamp_min", "aten::relu"),
    "indexing and copies": ("aten::index", "aten::index_put", "aten::copy_", "aten::cat", "aten::_to_copy"),
    "optimizer": ("Optimizer.step", "aten::_foreach"),
}
"""Operator-name prefixes of each group (the rest is `other`)."""


def group_of(name: str) -> str:
    return next((g for g, prefixes in GROUPS.items() if name.startswith(prefixes)), "other")


def fresh_learner(cfg: TrainConfig, threads: int) -> tuple[Learner, torch.Generator]:
    """A fresh learner and generator (seed 0) in the process state training runs in: malloc's thresholds kept
    (`bitcomm.learn.allocator`), `threads` torch threads."""
    keep_freed_memory()
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    return Learner(cfg), torch.Generator().manual_seed(0)


def time_parts(learner: Learner, cfg: TrainConfig, generator: torch.Generator, updates: int) -> dict[str, float]:
    """Milliseconds of one batch by part, medians over `updates` batches, without the profiler: playing it, and the
    update's critic and policy sides. On two threads the sync trainer runs the critic's loss and step beside the
    policy's (`bitcomm.learn.beside`), so a batch takes about play + advantages + the longer of the two; on one
    thread, or in an A3C worker, it takes their sum. The parts are timed by wrapping this learner's own methods."""
    import statistics
    import time

    spent: dict[str, float] = defaultdict(float)

    def timed(part: str | None, method: Any) -> Any:
        def run(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            out = method(*args, **kwargs)
            spent[part or ("critic: loss and step" if args[0] is learner.opt_critic else "policy: loss and step")] += (
                time.perf_counter() - t0
            )
            return out

        return run

    # instance attributes shadow the class's methods for this learner alone
    learner._critic_side = timed("critic: features and advantages", learner._critic_side)  # type: ignore[method-assign]
    learner._forward = timed("policy: forward", learner._forward)  # type: ignore[method-assign]
    learner.critic_loss = timed("critic: loss and step", learner.critic_loss)  # type: ignore[method-assign]
    learner._clipped_step = timed(None, learner._clipped_step)  # type: ignore[method-assign]
    rows: dict[str, list[float]] = defaultdict(list)
    collector = Collector(cfg.training_task, cfg.num_envs)
    for k in range(updates):
        t0 = time.perf_counter()
        ro = collector.collect(learner.policy, np.random.SeedSequence(k), generator)
        rows["play"].append(time.perf_counter() - t0)
        spent.clear()
        t0 = time.perf_counter()
        learner.update(ro, generator)
        rows["update"].append(time.perf_counter() - t0)
        for part, seconds in spent.items():
            rows[part].append(seconds)
        rows["policy: the rest (its loss terms, sampling)"].append(rows["update"][-1] - sum(spent.values()))
    return {part: 1000 * statistics.median(v) for part, v in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recipe", choices=tuple(RECIPES), default="reinforced")
    ap.add_argument("--updates", type=int, default=3, help="profiled updates (after one warm-up)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--num-envs", type=int, default=None, help="episodes in the batch (default: the recipe's)")
    ap.add_argument("--top", type=int, default=10, help="slowest operators listed")
    ap.add_argument("--size", type=int, default=EnvConfig.size, help="grid size (default %(default)s)")
    ap.add_argument("--bits", type=int, default=ChannelConfig.bits, help="message bits K (default %(default)s)")
    ap.add_argument("--messages", default=None, help="message head, bitwise or onehot (default: the recipe's)")
    a = ap.parse_args()
    try:  # bad input is one line before anything runs
        for name in ("updates", "threads", "top"):
            check_int(name, getattr(a, name), 1)
        task = TaskConfig(env=EnvConfig(size=a.size), channel=ChannelConfig(bits=a.bits))
        cfg = make_train_config(a.recipe, task, num_envs=a.num_envs, messages=a.messages, mode="sync")
    except ConfigError as err:
        ap.error(str(err))
    learner, generator = fresh_learner(cfg, a.threads)
    ro = Collector(cfg.training_task, cfg.num_envs).collect(learner.policy, np.random.SeedSequence(0), generator)
    learner.update(ro, generator)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(a.updates):
            learner.update(ro, generator)
    ops = [(e.key, e.self_cpu_time_total) for e in prof.key_averages()]
    total = sum(t for _, t in ops)
    shares: dict[str, float] = defaultdict(float)
    for name, t in ops:
        shares[group_of(name)] += t / total
    # one more update with the products' shapes recorded (which slows every operator, so the shares above are timed
    # without it): the operations the profiler counts, and the products' own time
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True, with_flops=True) as counting:
        learner.update(ro, generator)
    counted = [e for e in counting.key_averages() if e.flops]
    flops = sum(e.flops for e in counted)
    flops_s = sum(e.self_cpu_time_total for e in counted) / 1e6
    agent_steps = int(ro.length.sum()) * cfg.task.env.n_agents
    task_name = f"{a.size}x{a.size}, K={a.bits}, {cfg.model.messages}"
    per_update = total / 1e6 / a.updates
    print(
        f"{a.recipe} ({task_name}): {agent_steps:,} agent-steps per batch, "
        f"{cfg.epochs} epochs x {cfg.minibatches} minibatches, "
        f"{per_update:.3f} s of CPU per update ({a.threads} thread(s), profiler overhead included)"
    )
    for g, share in sorted(shares.items(), key=lambda kv: -kv[1]):
        print(f"  {g:20s} {100 * share:5.1f}%")
    print(
        f"matrix products: {flops / 1e9:.2f} GFLOP per update ({flops / agent_steps / 1e6:.2f} MFLOP per agent-step), "
        f"at {flops / 1e9 / max(flops_s, 1e-9):.1f} GFLOP/s"
    )
    print("slowest operators:")
    for name, t in sorted(ops, key=lambda kv: -kv[1])[: a.top]:
        print(f"  {name:40s} {100 * t / total:5.1f}%")
    summary = {
        "benchmark": "update_profile",
        "recipe": a.recipe,
        "task": task_name,
        "threads": a.threads,
        "agent_steps_per_batch": agent_steps,
        "cpu_s_per_update": round(per_update, 4),
        "shares": {g: round(s, 4) for g, s in shares.items()},
        "gflop_per_update": round(flops / 1e9, 3),
        "mflop_per_agent_step": round(flops / agent_steps / 1e6, 3),
        "matrix_gflop_per_s": round(flops / 1e9 / max(flops_s, 1e-9), 1),
    }
    parts = time_parts(learner, cfg, generator, a.updates)
    print(f"one batch by part, ms (median of {a.updates}, without the profiler):")
    for part, ms in parts.items():
        print(f"  {part:45s} {ms:7.1f}")
    summary["parts_ms"] = {part: round(ms, 1) for part, ms in parts.items()}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
