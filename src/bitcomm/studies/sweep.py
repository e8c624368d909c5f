"""Robustness sweeps: mean episode length as one noise parameter varies, the others held at the base task.

Each point is `bitcomm.policies.evaluation.evaluate` on the same seeded episode set, so the curves differ only
by the parameter (common random numbers). Reference policies are rebuilt for each task (the oracle
reads the message delay from it); a learned policy is the same network at every point, facing
conditions it may not have been trained on. Results go to a CSV and a figure (PNG and SVG) with one
panel per parameter.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bitcomm.config import TaskConfig
from bitcomm.errors import bad_value
from bitcomm.plotting import log_scale_suits, save_figure
from bitcomm.policies.agent_policies import BatchedPolicy
from bitcomm.policies.evaluation import EvalResult, evaluate
from bitcomm.policies.source import PolicySource
from bitcomm.studies.tables import write_rows_csv

# parameter -> (config part, type); what a robot meets that the paper's simulator lacks, plus message delay
SWEEPABLE: dict[str, tuple[str, type]] = {
    "act_fail_prob": ("env", float),
    "act_delay": ("env", int),
    "flip_prob": ("channel", float),
    "drop_prob": ("channel", float),
    "delay": ("channel", int),
}
DEFAULT_SWEEP: dict[str, tuple[float, ...]] = {
    "act_fail_prob": (0.0, 0.1, 0.2, 0.3),
    "act_delay": (0, 1, 2, 3),
    "flip_prob": (0.0, 0.01, 0.02, 0.05, 0.1),
    "drop_prob": (0.0, 0.1, 0.2, 0.3, 0.5),
}
CSV_FIELDS = ("policy", "param", "value", "episodes", "mean_episode_length", "ci95_low", "ci95_high",
              "mean_team_return", "success_rate")  # fmt: skip


@dataclass(frozen=True)
class SweepPoint:
    policy: str
    param: str
    value: float
    result: EvalResult

    def row(self) -> dict[str, object]:
        r = self.result
        return {
            "policy": self.policy, "param": self.param, "value": self.value, "episodes": r.episodes,
            "mean_episode_length": r.mean_episode_length, "ci95_low": r.ci95[0], "ci95_high": r.ci95[1],
            "mean_team_return": r.mean_team_return, "success_rate": r.success_rate,
        }  # fmt: skip


def parse_param(text: str) -> tuple[str, tuple[float, ...]]:
    """`name=v1,v2,...` (dashes allowed in the name) -> (name, values), typed by the parameter."""
    name, sep, values = text.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or name not in SWEEPABLE:
        raise bad_value("param", text, f"expected NAME=V1,V2,... with NAME one of {', '.join(SWEEPABLE)}")
    kind = SWEEPABLE[name][1]
    try:
        parsed = tuple(float(v) for v in values.split(",") if v.strip())
    except ValueError:
        raise bad_value("param", text, "values must be numbers") from None
    if not parsed:
        raise bad_value("param", text, "give at least one value")
    if len(set(parsed)) != len(parsed):
        raise bad_value("param", text, "values repeat")
    if kind is int:
        if not all(math.isfinite(v) and v == int(v) for v in parsed):  # int() of NaN or inf is a traceback
            raise bad_value(name, values, "must be whole numbers")
        return name, tuple(int(v) for v in parsed)
    return name, parsed


def with_param(task: TaskConfig, name: str, value: float) -> TaskConfig:
    """`task` with one parameter changed (validated by the configs)."""
    part, kind = SWEEPABLE[name]
    if part == "env":
        return TaskConfig(dataclasses.replace(task.env, **{name: kind(value)}), task.channel)
    return TaskConfig(task.env, dataclasses.replace(task.channel, **{name: kind(value)}))


def run_sweep(
    sources: list[PolicySource],
    task: TaskConfig,
    params: dict[str, tuple[float, ...]],
    episodes: int = 1000,
    seed: int = 0,
) -> list[SweepPoint]:
    """Every (policy, parameter, value) point, each on the same seeded episode set."""
    tasks = {(name, v): with_param(task, name, v) for name, values in params.items() for v in values}  # fail early
    points = []
    for source in sources:
        for (name, value), point_task in tasks.items():
            policy = BatchedPolicy(source.build(point_task, seed=seed))
            points.append(SweepPoint(source.label, name, value, evaluate(policy, point_task, episodes, seed)))
    return points


def write_csv(points: list[SweepPoint], path: str | Path) -> Path:
    return write_rows_csv((p.row() for p in points), CSV_FIELDS, path)


def plot_sweep(points: list[SweepPoint], path: str | Path, title: str = "") -> list[Path]:
    """One panel per parameter: mean episode length (95% interval as bars) against its value, a line per policy.

    Written as `path` in PNG and beside it in SVG; returns both paths.
    """
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    params = list(dict.fromkeys(p.param for p in points))
    policies = list(dict.fromkeys(p.policy for p in points))
    fig = Figure(figsize=(3.6 * len(params) + 0.4, 3.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(params), squeeze=False)).ravel()
    log_scale = log_scale_suits([p.result.mean_episode_length for p in points])
    for ax, param in zip(axes, params, strict=True):
        for policy in policies:
            pts = sorted((p for p in points if p.param == param and p.policy == policy), key=lambda p: p.value)
            x = np.array([p.value for p in pts])
            y = np.array([p.result.mean_episode_length for p in pts])
            ci = np.array([p.result.ci95 for p in pts]).reshape(-1, 2)
            err = np.stack([y - ci[:, 0], ci[:, 1] - y])
            ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=policy)
        ax.set_xlabel(param)
        ax.set_ylabel("mean episode length")
        if log_scale:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
