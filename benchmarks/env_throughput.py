"""Throughput of the environment and its channel, in agent-steps per second.

Times `VecGoalExchange.step` + `observe` (so building the planes a policy consumes counts) on the
default task, with uniform random moves and bits drawn before the timed loop. Each batch size is
timed `--repeats` times and the median is reported; the last line is a JSON object mapping B to
agent-steps/s. The timed loop is longer than an episode (random play runs to the 256-step
truncation), so every episode's reset is inside the timing too.

    python benchmarks/env_throughput.py [--sizes 64 512 4096] [--steps 300] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from bitcomm.config import TaskConfig
from bitcomm.envs.vec import VecGoalExchange

POOL = 64  # distinct pre-drawn action batches, cycled through in the timed loop


def agent_steps_per_second(task: TaskConfig, num_envs: int, steps: int, seed: int = 0) -> float:
    """One timed run: `steps` steps of `num_envs` episodes, random actions drawn in advance."""
    n, K = task.env.n_agents, task.channel.bits
    rng = np.random.default_rng(seed)
    moves = rng.integers(0, 5, size=(POOL, num_envs, n))
    bits = rng.integers(0, 2, size=(POOL, num_envs, n, K), dtype=np.uint8)
    env = VecGoalExchange(task, num_envs, seed=seed)
    for k in range(10):  # warm-up: caches, allocator, first resets
        env.step(moves[k % POOL], bits[k % POOL])
        env.observe()
    start = time.perf_counter()
    for k in range(steps):
        env.step(moves[k % POOL], bits[k % POOL])
        env.observe()
    elapsed = time.perf_counter() - start
    return steps * num_envs * n / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 512, 4096], help="batch sizes B")
    parser.add_argument("--steps", type=int, default=300, help="timed steps per run (> max_steps: resets count)")
    parser.add_argument("--repeats", type=int, default=5, help="runs per batch size; the median is reported")
    args = parser.parse_args()
    task = TaskConfig()
    medians: dict[int, float] = {}
    for B in args.sizes:
        runs = [agent_steps_per_second(task, B, args.steps, seed=r) for r in range(args.repeats)]
        medians[B] = statistics.median(runs)
        spread = ", ".join(f"{r / 1e6:.2f}" for r in runs)
        print(f"B={B:5d}: median {medians[B] / 1e6:.2f} M agent-steps/s (runs: {spread})", flush=True)
    print(json.dumps({str(B): round(v) for B, v in medians.items()}))


if __name__ == "__main__":
    main()
