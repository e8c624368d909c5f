"""What flushing denormals is worth (`bitcomm.policies.denormals`): a trained run's batch, updated with the CPU's
flush-to-zero mode on and off, taking turns.

The slow path for denormal floats bites late in training, when the policy is nearly deterministic, so this
times the update on batches played by a trained checkpoint (`RUN`: a run folder or checkpoint, any task or
head), not by a fresh policy. It plays `--batches` batches, makes one warm-up update, then for `--rounds` rounds
plays the batches again and updates each with flushing on, then with it off (the mode belongs to the thread,
so one process measures both), putting the weights and optimizer state back after each update, so every update
starts from the checkpoint. Prints the medians, the ratio off/on and the agent-steps per second of a batch,
collection included; the last line printed is one JSON object.

    python benchmarks/denormals.py RUN [--rounds 3] [--batches 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from bitcomm.checkpoint import load_weights
from bitcomm.errors import ConfigError, check_int
from bitcomm.learn.beside import critic_beside_policy
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.rollout import Collector, Rollout
from bitcomm.policies.denormals import flush_denormals
from update_profile import fresh_learner  # benchmarks/ is not a package

SETTINGS: dict[str, Callable[[], contextlib.AbstractContextManager[object]]] = {
    "on": flush_denormals,
    "off": contextlib.nullcontext,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a trained run folder or checkpoint (its batches are the late-training ones)")
    ap.add_argument("--rounds", type=int, default=3, help="updates of each batch per setting, taking turns")
    ap.add_argument("--batches", type=int, default=2, help="batches played by the checkpoint")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (2: the critic beside the policy)")
    a = ap.parse_args()
    try:  # bad input is one line before anything runs
        for name in ("rounds", "batches", "threads"):
            check_int(name, getattr(a, name), 1)
        weights, info = load_weights(a.run)
        cfg = TrainConfig.from_dict(info["config"])
    except ConfigError as err:
        ap.error(str(err))
    learner, generator = fresh_learner(cfg, a.threads)
    learner.policy.load_state_dict(weights["policy"])
    learner.critic.load_state_dict(weights["critic"])
    collector = Collector(cfg.training_task, cfg.num_envs)

    def play() -> list[Rollout]:  # the same batches every time: a generator of their own each
        gens = [torch.Generator().manual_seed(k) for k in range(a.batches)]
        return [collector.collect(learner.policy, np.random.SeedSequence(k), g) for k, g in enumerate(gens)]

    trained: tuple[Any, ...] = (learner.policy, learner.critic, learner.opt_policy, learner.opt_critic)
    saved = [copy.deepcopy(m.state_dict()) for m in trained]

    def restore() -> None:  # each timed update starts from the checkpoint
        for m, state in zip(trained, saved, strict=True):
            m.load_state_dict(state)

    collect_s: dict[str, list[float]] = {s: [] for s in SETTINGS}
    update_s: dict[str, list[float]] = {s: [] for s in SETTINGS}
    with critic_beside_policy(learner, a.threads):
        batches = play()
        learner.update(batches[0], generator)  # warm-up
        restore()
    for r in range(a.rounds):
        for setting, mode in SETTINGS.items():
            with mode(), critic_beside_policy(learner, a.threads):  # the helper thread takes the mode
                t0 = time.perf_counter()
                batches = play()
                collect_s[setting].append((time.perf_counter() - t0) / a.batches)
                for ro in batches:
                    t0 = time.perf_counter()
                    learner.update(ro, generator)
                    update_s[setting].append(time.perf_counter() - t0)
                    restore()
        print(f"round {r + 1}: " + ", ".join(f"{s} {np.median(v[-a.batches :]):.4f} s" for s, v in update_s.items()))
    steps = float(np.mean([int(ro.length.sum()) * cfg.task.env.n_agents for ro in batches]))
    med = {s: float(np.median(v)) for s, v in update_s.items()}
    collect = {s: float(np.median(v)) for s, v in collect_s.items()}
    rate = {s: steps / (collect[s] + med[s]) for s in SETTINGS}
    task = f"{cfg.task.env.size}x{cfg.task.env.size}, K={cfg.task.channel.bits}, {cfg.model.messages}"
    print(
        f"{task}, {steps:,.0f} agent-steps per batch: update {med['off']:.4f} s -> {med['on']:.4f} s "
        f"({med['off'] / med['on']:.2f}x); {rate['off']:,.0f} -> {rate['on']:,.0f} agent-steps/s with collection "
        f"(medians of {a.rounds * a.batches} updates each, {a.threads} thread(s))"
    )
    summary = {
        "benchmark": "denormals",
        "run": info["path"],
        "task": task,
        "threads": a.threads,
        "agent_steps_per_batch": steps,
        "median_update_s": {s: round(v, 4) for s, v in med.items()},
        "median_collect_s": {s: round(v, 4) for s, v in collect.items()},
        "update_speedup": round(med["off"] / med["on"], 3),
        "agent_steps_per_s": {s: round(v) for s, v in rate.items()},
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
