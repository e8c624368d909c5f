"""Episodes per second of `play` with the env copies in the learner's process against W worker processes.

What it shows: where stepping the B copies one at a time is what a batch waits on, `--env-workers W`
(`SubprocVecEnv`) steps W shares of them at once. Two envs: MPE2 speaker-listener as it is (a fast,
CPU-bound env: a gain needs idle cores, and the pipes cost something per step), and the same env made slow
by a wrapper that sleeps `--step-ms` per step of each copy (an env that waits on a simulator or a device:
its copies overlap even on busy cores). The policy is an untrained `MlpPolicy`, sampling; every setting plays
the same seeded episodes. Each setting times `--batches` batches of `--num-envs` episodes after one warm-up
batch, `--repeats` times in this one process run, and reports the median; worker start-up is not timed
(it is paid once per run). The last line is JSON: env -> setting -> median episodes/s.

    python benchmarks/env_vector_speed.py [--num-envs 32] [--batches 2] [--repeats 3] [--step-ms 2] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from typing import Any

from pettingzoo import ParallelEnv
from pettingzoo.utils.wrappers.base_parallel import BaseParallelWrapper

# Nothing heavy at the top: each worker process imports this module (the slow env's factory is here).
MPE = "mpe2.simple_speaker_listener_v4:parallel_env"
SLOW = "env_vector_speed:slow_env"  # `python benchmarks/env_vector_speed.py` puts benchmarks/ on sys.path


class SlowEnv(BaseParallelWrapper):
    """An env whose every step takes `step_ms` longer (sleeping: no CPU)."""

    def __init__(self, env: ParallelEnv, step_ms: float) -> None:
        super().__init__(env)
        self.step_ms = step_ms

    def step(self, actions: dict[str, Any]) -> Any:
        time.sleep(self.step_ms / 1000)
        return self.env.step(actions)


def slow_env(spec: str, step_ms: float, **kwargs: Any) -> SlowEnv:
    from bitcomm.envs.factory import make_parallel_env

    return SlowEnv(make_parallel_env(spec, kwargs), step_ms)


def episodes_per_second(env: str, env_kwargs: dict[str, Any], workers: int, args: argparse.Namespace) -> list[float]:
    """`--repeats` timings of `--batches` batches of `play` (after a warm-up batch) with `workers` processes."""
    import numpy as np
    import torch

    from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
    from bitcomm.learn.env_learner import EnvLearner
    from bitcomm.learn.env_rollout import make_vec, play

    cfg = EnvTrainConfig(env=env, env_kwargs=env_kwargs, channel=EnvChannelConfig(bits=3), num_envs=args.num_envs)
    with make_vec(cfg, cfg.num_envs, workers=workers) as vec:
        torch.manual_seed(0)
        policy = EnvLearner(cfg, vec.layout).policy
        generator = torch.Generator().manual_seed(0)
        play(vec, policy, np.random.SeedSequence(0), generator)  # warm-up
        runs = []
        for r in range(args.repeats):
            start = time.perf_counter()
            for k in range(args.batches):
                play(vec, policy, np.random.SeedSequence(1, spawn_key=(r, k)), generator)
            runs.append(args.batches * args.num_envs / (time.perf_counter() - start))
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num-envs", type=int, default=32, help="copies of the env, episodes per batch")
    parser.add_argument("--batches", type=int, default=2, help="timed batches per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per setting; the median is reported")
    parser.add_argument("--step-ms", type=float, default=2.0, help="the slow env's extra time per step of a copy")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to compare with 0")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the learner's process")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    envs = {
        "mpe2 speaker-listener": (MPE, {}),
        f"mpe2 speaker-listener, {args.step_ms:g} ms/step": (SLOW, {"spec": MPE, "step_ms": args.step_ms}),
    }
    medians: dict[str, dict[str, float]] = {}
    for name, (spec, kwargs) in envs.items():
        medians[name] = {}
        for w in [0, *args.workers]:
            runs = episodes_per_second(spec, kwargs, w, args)
            setting = "in-process" if w == 0 else f"{w} worker{'s' if w > 1 else ''}"
            median = medians[name][setting] = round(statistics.median(runs), 1)
            spread = ", ".join(f"{x:.1f}" for x in runs)
            print(f"{name:36s} {setting:11s} median {median:8.1f} episodes/s (runs: {spread})", flush=True)
    print(json.dumps(medians))


if __name__ == "__main__":
    main()
