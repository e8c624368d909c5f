"""What a message head costs as the grid grows (paper III-A): bitwise K outputs against one-hot 2^K.

For a grid of S cells a side the message carries K = ceil(log2(S^2)) bits, just enough to name any
cell. For each S and each head, with the networks of one recipe:

- outputs: the message head's (K against 2^K) and the policy's (5 moves + those);
- parameters: the policy, the V1 critic (standard estimator: it reads the received message, so it
  grows with the head) and the V2 critic (improved: it does not);
- memory: bytes of the float32 parameters a learner holds (policy + the estimator's critic), and the
  peak tensor memory of one learner update, measured with the torch profiler on CPU (the running sum
  of the allocations and frees it records, from the start of the update; the Python heap is not counted);
- time: one `Learner.update` on a fixed small batch of episodes, median of a few repeats.

Optionally, a training run per size and head at a fixed budget, skipped where the training update is
estimated to need more than `max_memory_gb` (the measured peak, scaled to a full training batch).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import os
import statistics
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import bad_value, check_int
from bitcomm.learn.config import TrainConfig, make_train_config
from bitcomm.learn.learner import Learner
from bitcomm.learn.recipes import DEFAULT_RECIPE
from bitcomm.learn.rollout import Collector, Rollout
from bitcomm.plotting import save_figure
from bitcomm.policies.heads import MESSAGE_HEADS
from bitcomm.policies.networks import CriticNet, PolicyNet
from bitcomm.studies.tables import write_rows_csv

DEFAULT_SIZES = (10, 16, 32, 64)
FLOAT_BYTES = 4
ADAM_COPIES = 4
"""Training memory per parameter: the weight, its gradient and Adam's two moments."""
CSV_FIELDS = (
    "size", "bits", "messages", "message_outputs", "policy_outputs", "message_head_params", "message_input_params",
    "policy_params", "critic_v1_params", "critic_v2_params", "param_bytes", "update_peak_bytes", "update_seconds",
    "batch_samples", "train_memory_gb", "episodes", "final_episode_length",
)  # fmt: skip


def bits_for(size: int) -> int:
    """K = ceil(log2(size^2)): the fewest bits that name every cell of the grid."""
    return (size * size - 1).bit_length()


@dataclass(frozen=True)
class ScalingConfig:
    """What to measure; the update batch is small on purpose, so 64x64 one-hot stays cheap."""

    sizes: tuple[int, ...] = DEFAULT_SIZES
    recipe: str = DEFAULT_RECIPE
    """Networks and update of this recipe (`bitcomm.learn.config.RECIPES`)."""
    estimator: str = "improved"
    batch_episodes: int = 8
    """Episodes in the fixed batch of the timed update."""
    batch_steps: int = 32
    """Steps each of those episodes is truncated at (an untrained policy would wander for max_steps)."""
    repeats: int = 5
    """Timed updates (after one warm-up); the median is reported."""
    episodes: int = 0
    """Training budget per size and head for the learning curves; 0 skips them."""
    num_envs: int | None = None
    """Episodes per training batch of those runs (None: the recipe's)."""
    max_memory_gb: float = 8.0
    """Train only where the estimated training-update memory fits in this."""
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.sizes or any(not isinstance(s, int) or s < 2 for s in self.sizes):
            raise bad_value("sizes", self.sizes, "grid sides must be integers >= 2")
        for name in ("batch_episodes", "batch_steps", "repeats"):
            check_int(name, getattr(self, name), 1)
        if self.num_envs is not None:
            check_int("num_envs", self.num_envs, 1)
        if self.episodes < 0:
            raise bad_value("episodes", self.episodes, "must be >= 0 (0 skips training)")
        if not self.max_memory_gb > 0:
            raise bad_value("max-memory-gb", self.max_memory_gb, "must be > 0")


@dataclass(frozen=True)
class ScalingRow:
    size: int
    bits: int
    messages: str
    message_outputs: int
    policy_outputs: int
    message_head_params: int
    """The layer giving the message logits: (hidden + 1) x message_outputs."""
    message_input_params: int
    """The layer reading the received message: (slots x receiver inputs + 1) x message_hidden."""
    policy_params: int
    critic_v1_params: int
    critic_v2_params: int
    param_bytes: int
    """float32 parameters a learner holds: the policy and the estimator's critic."""
    update_peak_bytes: int
    update_seconds: float
    batch_samples: int
    """Agent-steps in the timed batch."""
    train_memory_gb: float
    """Estimated memory of a training update: ADAM_COPIES x param_bytes + the peak per sample x a full batch."""
    episodes: int = 0
    final_episode_length: float | None = None
    """Rolling mean episode length at the end of the training run (None when not trained)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def parse_sizes(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise bad_value("sizes", text, "expected comma-separated grid sides, e.g. 10,16,32,64") from None
    if not sizes:
        raise bad_value("sizes", text, "give at least one grid side")
    return sizes


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def train_config(size: int, messages: str, scfg: ScalingConfig, episodes: int | None = None) -> TrainConfig:
    """The recipe's config on the S x S task with K = bits_for(S) and the given head."""
    task = TaskConfig(EnvConfig(size=size), ChannelConfig(bits=bits_for(size)))
    options = dict(messages=messages, estimator=scfg.estimator, seed=scfg.seed, episodes=episodes)
    return make_train_config(scfg.recipe, task, num_envs=scfg.num_envs, **options)


def fixed_batch(cfg: TrainConfig, scfg: ScalingConfig, policy: PolicyNet) -> Rollout:
    """`batch_episodes` episodes of at most `batch_steps` steps, played by the (untrained) policy."""
    env = dataclasses.replace(cfg.task.env, max_steps=scfg.batch_steps)
    collector = Collector(TaskConfig(env, cfg.task.channel), scfg.batch_episodes)
    generator = torch.Generator().manual_seed(scfg.seed)
    return collector.collect(policy, np.random.SeedSequence(scfg.seed), generator)


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence file descriptor 2 (the profiler's C++ library logs each start and stop there)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def peak_update_bytes(learner: Learner, ro: Rollout) -> int:
    """Peak tensor memory of one `learner.update(ro)` above its start, from the profiler's records."""
    from torch.profiler import ProfilerActivity, profile

    with _quiet_stderr(), profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        learner.update(ro, torch.Generator().manual_seed(0))
    # every allocation (+bytes) and free (-bytes) as recorded; the raw records, as building the
    # profiler's per-op summary of a whole update takes seconds
    records = [e for e in prof.profiler.kineto_results.events() if e.name() == "[memory]"]
    running = peak = 0
    for event in sorted(records, key=lambda e: e.start_ns()):
        running += event.nbytes()
        peak = max(peak, running)
    return peak


def update_seconds(learner: Learner, ro: Rollout, repeats: int) -> float:
    """Median wall time of `repeats` updates, after one warm-up."""
    generator = torch.Generator().manual_seed(0)
    learner.update(ro, generator)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        learner.update(ro, generator)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(size: int, messages: str, scfg: ScalingConfig) -> ScalingRow:
    """Sizes, memory and update time of one (grid size, head) pair."""
    cfg = train_config(size, messages, scfg)
    with torch.random.fork_rng():
        torch.manual_seed(scfg.seed)
        learner = Learner(cfg)
        v1 = CriticNet(cfg.task, cfg.model, with_message=True)
        v2 = CriticNet(cfg.task, cfg.model, with_message=False)
        ro = fixed_batch(cfg, scfg, learner.policy)
        peak = peak_update_bytes(learner, ro)
        seconds = update_seconds(learner, ro, scfg.repeats)
    policy = learner.policy
    param_bytes = FLOAT_BYTES * (count(policy) + count(learner.critic))
    samples = int(ro.valid.sum()) * cfg.task.env.n_agents
    full_batch = cfg.num_envs * cfg.task.env.max_steps * cfg.task.env.n_agents  # every episode to truncation
    train_bytes = ADAM_COPIES * param_bytes + peak / max(samples, 1) * full_batch
    return ScalingRow(
        size=size,
        bits=cfg.task.channel.bits,
        messages=messages,
        message_outputs=policy.head.out_features,
        policy_outputs=policy.move_logits.out_features + policy.head.out_features,
        message_head_params=count(policy.message_logits),
        message_input_params=count(policy.message_in),
        policy_params=count(policy),
        critic_v1_params=count(v1),
        critic_v2_params=count(v2),
        param_bytes=param_bytes,
        update_peak_bytes=peak,
        update_seconds=seconds,
        batch_samples=samples,
        train_memory_gb=train_bytes / 2**30,
    )


def learning_run(row: ScalingRow, scfg: ScalingConfig, out: Path, progress: bool = False) -> ScalingRow:
    """Train the pair for `scfg.episodes` episodes into `out` (skipped when over the memory limit); a run that
    has played them is kept and one stopped short of them resumed, so the study can be called again."""
    from bitcomm.learn.run import train
    from bitcomm.studies.compare import folder_status

    if row.train_memory_gb > scfg.max_memory_gb:
        return row
    cfg = train_config(row.size, row.messages, scfg, episodes=scfg.episodes)
    cfg = dataclasses.replace(cfg, checkpoint_seconds=1e9)
    status = folder_status(out, cfg)
    if status != "done":
        train(cfg, out, resume=status == "resume", progress=progress)
    with (out / "metrics.csv").open(newline="") as f:
        last = list(csv.DictReader(f))[-1]
    return dataclasses.replace(
        row, episodes=int(last["episodes"]), final_episode_length=float(last["charts/episode_length_rolling"])
    )


def run_scaling(scfg: ScalingConfig, out: Path | None = None, progress: bool = False) -> list[ScalingRow]:
    """Every (size, head) row; with `scfg.episodes` > 0 also a run each in `out/runs/<size>_<head>`."""
    rows = [measure(size, messages, scfg) for size in scfg.sizes for messages in MESSAGE_HEADS]
    if scfg.episodes > 0:
        assert out is not None, "training runs need a folder"
        rows = [learning_run(r, scfg, out / "runs" / f"{r.size}_{r.messages}", progress) for r in rows]
    return rows


# ---------------------------------------------------------------------------------------------- report
def write_csv(rows: list[ScalingRow], path: str | Path) -> Path:
    return write_rows_csv((r.to_dict() for r in rows), CSV_FIELDS, path)


def _mib(n: float) -> str:
    return f"{n / 2**20:.2f}"


def markdown_table(rows: list[ScalingRow], scfg: ScalingConfig) -> str:
    trained = any(r.episodes > 0 for r in rows)
    head = "| grid | K | head | message outputs | policy params | V1 params | V2 params | param MiB | update peak MiB "
    head += "| update ms |" + (" final episode length |" if trained else "")
    lines = [
        "# Bitwise against one-hot messages as the grid grows",
        "",
        f"Networks and update of the `{scfg.recipe}` recipe, `{scfg.estimator}` estimator. Update: one "
        f"`Learner.update` on {scfg.batch_episodes} episodes of at most {scfg.batch_steps} steps, median of "
        f"{scfg.repeats}; its peak is the tensor memory recorded by the torch profiler on CPU. Param MiB: float32 "
        "policy + the estimator's critic.",
        "",
        head,
        "| ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |" + (" ---: |" if trained else ""),
    ]
    for r in rows:
        line = (
            f"| {r.size}x{r.size} | {r.bits} | {r.messages} | {r.message_outputs} | {r.policy_params:,} | "
            f"{r.critic_v1_params:,} | {r.critic_v2_params:,} | {_mib(r.param_bytes)} | {_mib(r.update_peak_bytes)} | "
            f"{1000 * r.update_seconds:.1f} |"
        )
        if trained:
            length = r.final_episode_length
            line += f" {length:.1f} |" if length is not None else " not trained (memory) |"
        lines.append(line)
    return "\n".join(lines) + "\n"


PANELS = (
    ("message_outputs", "message head outputs"),
    ("policy_params", "policy parameters"),
    ("update_seconds", "one update (s)"),
    ("update_peak_bytes", "update peak memory (bytes)"),
)


def plot_scaling(rows: list[ScalingRow], path: str | Path) -> list[Path]:
    """Each measure against K, log y, a line per head; written as `path` (PNG) and beside it as SVG; returns both
    paths."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    fig = Figure(figsize=(3.4 * len(PANELS) + 0.4, 3.4), layout="constrained")
    axes = fig.subplots(1, len(PANELS), squeeze=False)[0]
    for ax, (field, label) in zip(axes, PANELS, strict=True):
        for messages in MESSAGE_HEADS:
            pts = sorted((r for r in rows if r.messages == messages), key=lambda r: r.bits)
            ax.plot([r.bits for r in pts], [max(getattr(r, field), 1e-12) for r in pts], marker="o", label=messages)
        ax.set_yscale("log")
        ax.set_xlabel("message bits K")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    sizes = sorted({(r.bits, r.size) for r in rows})
    axes[0].legend(fontsize=8)
    fig.suptitle("grid sides " + ", ".join(f"{s} (K={k})" for k, s in sizes), fontsize=10)
    return save_figure(fig, path)


def plot_curves(out: Path, rows: list[ScalingRow]) -> list[Path]:
    """Learning curves of the training runs (from their metrics.csv), a panel per grid size, as
    scaling_curves.png and .svg; returns their paths, none when nothing was trained."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    trained = [r for r in rows if r.episodes > 0]
    if not trained:
        return []
    sizes = sorted({r.size for r in trained})
    fig = Figure(figsize=(4 * len(sizes) + 0.4, 3.4), layout="constrained")
    axes = fig.subplots(1, len(sizes), squeeze=False)[0]
    for ax, size in zip(axes, sizes, strict=True):
        for r in (r for r in trained if r.size == size):
            with (out / "runs" / f"{r.size}_{r.messages}" / "metrics.csv").open(newline="") as f:
                metrics = list(csv.DictReader(f))
            x = [float(m["episodes"]) for m in metrics]
            ax.plot(x, [float(m["charts/episode_length_rolling"]) for m in metrics], label=r.messages)
        ax.set_title(f"{size}x{size}, K = {bits_for(size)}", fontsize=10)
        ax.set_xlabel("episodes")
        ax.set_ylabel("mean episode length")
        ax.legend(fontsize=8)
    return save_figure(fig, out / "scaling_curves.png")
