"""The four-technique study on a wrapped PettingZoo env (`bitcomm compare --env`), the grid study's twin.

Each technique (and `no-comm`: improved + bitwise trained with every message dropped) is trained over
seeds with `train_env` on the env and channel of `EnvCompareConfig.base`, then measured on one evaluation
episode set: sampled, greedy, and sampled with the channel cut (`cut`: the same policy with every message
dropped; a policy that learned to communicate loses return there, one that did not loses nothing). There is
no oracle on an arbitrary env, so the study reports the mean team return (higher is better) and its 95%
interval over seeds, at equal episodes and at equal wall-clock, not times to a level.

The folder layout, the skipping of finished runs and resuming of partial ones, the process pool and the
evaluation record are the grid study's (`bitcomm.studies.compare`); only the measures differ.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from bitcomm.files import write_text_atomic
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.plotting import save_figure
from bitcomm.studies.compare import (
    CHOICES,
    ENV_STUDY_SEEDS,
    NO_COMM,
    PLAYS,
    TECHNIQUES,
    VERBS,
    Configuration,
    Run,
    along_budget,
    along_budget_markdown,
    budget_marks,
    cell,
    check_budget,
    check_study_fields,
    draw_seed_band,
    evaluation_of,
    execute_all,
    first_logged,
    interval,
    machines_sentence,
    markdown_header,
    markdown_row,
    per_seed_markdown,
    read_columns,
    read_evaluation,
    run_record,
    runs_phrase,
    seconds_phrase,
    study_runs,
    study_seeds,
    technique_entry,
    write_curves_csv,
)

CURVE_COLUMNS = ("team_return_rolling", "team_return", "episode_length")
"""The `charts/` columns of a wrapped-env run's metrics.csv an `EnvCurve` holds (and curves.csv's names)."""
MEASURES = ("mean_team_return", "mean_episode_length")
"""What the table and summary give of each play (`bitcomm.learn.env_eval.EnvEvalResult`)."""


@dataclass(frozen=True)
class EnvCompareConfig:
    """One study on a wrapped env; `bitcomm compare --env`'s flags one for one."""

    base: EnvTrainConfig
    """The env, its channel, the budget and the learning options of every run; each run sets its own
    estimator, message head and seed (and `no-comm` its drop probability to 1)."""
    out: Path = Path("runs/compare-env")
    techniques: tuple[str, ...] = CHOICES
    seeds: int = ENV_STUDY_SEEDS
    first_seed: int = 0
    """Seeds first_seed .. first_seed + seeds - 1 of every technique (see `CompareConfig.first_seed`)."""
    jobs: int = field(default_factory=lambda: os.cpu_count() or 1)
    eval_episodes: int = 1000
    eval_seed: int = 1000
    report: bool = False
    """Train nothing: report the runs that have played their budget."""

    def __post_init__(self) -> None:
        check_study_fields(self)


class EnvCurve(NamedTuple):
    """A wrapped-env run's learning curve, one entry per logged batch (metrics.csv)."""

    episodes: np.ndarray
    wall_s: np.ndarray
    return_rolling: np.ndarray
    team_return: np.ndarray
    length: np.ndarray


def read_env_curve(folder: Path) -> EnvCurve:
    return EnvCurve(*read_columns(folder, CURVE_COLUMNS))


def run_config(cfg: EnvCompareConfig, technique: str, seed: int) -> EnvTrainConfig:
    estimator, messages = TECHNIQUES.get(technique, TECHNIQUES["improved-bitwise"])
    channel = cfg.base.channel
    if technique == NO_COMM:
        channel = dataclasses.replace(channel, drop_prob=1.0)
    return dataclasses.replace(cfg.base, estimator=estimator, messages=messages, seed=seed, channel=channel)


def plan(cfg: EnvCompareConfig) -> list[Run]:
    """Every run of the study, seed by seed (a study stopped early has every technique's first seeds)."""
    return check_budget(
        [
            Run(Configuration(t), seed, run_config(cfg, t, seed), cfg.out / "runs" / t / f"seed{seed}")
            for seed in study_seeds(cfg)
            for t in cfg.techniques
        ]
    )


def describe(run: Run, status: str, cfg: EnvCompareConfig) -> str:
    """One progress line for a finished run."""
    curve = read_env_curve(run.folder)
    evaluation = read_evaluation(run, cfg.eval_episodes, cfg.eval_seed) or {}
    sampled, cut = (evaluation.get(p, {}).get("mean_team_return", math.nan) for p in ("sampled", "cut"))
    return (
        f"{run.configuration.name} seed {run.seed}: {VERBS[status]} to {int(curve.episodes[-1])} episodes in "
        f"{curve.wall_s[-1]:.1f} s, rolling mean team return {curve.return_rolling[-1]:.3f}, evaluated "
        f"{sampled:.3f} (sampled), {cut:.3f} with the channel cut"
    )


def summarize(cfg: EnvCompareConfig, runs: list[Run], curves: dict[Path, EnvCurve]) -> dict[str, Any]:
    """summary.json: the study and, per technique, its runs and their intervals (equal episodes: the end of
    the budget; equal wall-clock: every run read at the quickest run's training time)."""
    equal_wall = min(float(curves[r.folder].wall_s[-1]) for r in runs)
    marks = budget_marks(cfg.base.episodes, first_logged(curves[r.folder] for r in runs))
    configurations = []
    for conf in dict.fromkeys(r.configuration for r in runs):
        records = []
        for run in (r for r in runs if r.configuration == conf):
            curve, evaluation = curves[run.folder], evaluation_of(run, cfg)
            record = run_record(run, curve, cfg.out, equal_wall, marks, "return_rolling", "team_return")
            records.append({**record, **{play: evaluation[play] for play in PLAYS}})
        entry: dict[str, Any] = {
            **technique_entry(conf),
            "seeds": len(records),
            "wall_s": interval([r["wall_s"] for r in records]),
            "final_rolling_team_return": interval([r["final_rolling_team_return"] for r in records]),
            "rolling_at_equal_wall": interval([r["rolling_at_equal_wall"] for r in records]),
            "rolling_at_episodes": along_budget(records, marks),
        }
        for play in PLAYS:
            entry[play] = {key: interval([r[play][key] for r in records]) for key in MEASURES}
        entry["runs"] = records
        configurations.append(entry)
    base = cfg.base.to_dict()
    return {
        "study": {
            "env": cfg.base.env,
            "env_kwargs": cfg.base.env_kwargs,
            "channel": base.pop("channel"),
            "episodes": cfg.base.episodes,
            "seeds": cfg.seeds,
            "first_seed": cfg.first_seed,
            "report": cfg.report,
            "techniques": list(cfg.techniques),
            "learning": {
                k: v
                for k, v in base.items()
                if k not in ("env", "env_kwargs", "estimator", "messages", "seed", "episodes")
            },  # fmt: skip
            "eval_episodes": cfg.eval_episodes,
            "eval_seed": cfg.eval_seed,
            "equal_wall_s": equal_wall,
            "episode_marks": marks,
        },
        "configurations": configurations,
    }


def table_markdown(summary: dict[str, Any]) -> str:
    """table.md: one row per technique, mean ± 95% half-interval over seeds."""
    study, ch = summary["study"], summary["study"]["channel"]
    header = ["configuration", "seeds", "return (sampled)", "return (greedy)", "return, channel cut at evaluation",
              "episode length (sampled)", "rolling return at the end",
              f"rolling return after {seconds_phrase(study['equal_wall_s'])}", "seconds per run"]  # fmt: skip
    lines = [
        f"# bitcomm compare: {study['env']}, {runs_phrase(study, summary['configurations'])}",
        "",
        f"Env kwargs {json.dumps(study['env_kwargs'])}; channel K = {ch['bits']} bits, delay {ch['delay']}, flip "
        f"{ch['flip_prob']:g}, drop {ch['drop_prob']:g}, topology {json.dumps(ch['topology'])}. Evaluation: "
        f"{study['eval_episodes']} episodes of seed {study['eval_seed']}: sampled, greedy, and sampled with every "
        "message dropped (the channel cut: what the same policy does without communication).",
        "Each cell is the mean team return (higher is better) ± the 95% half-interval over seeds (Student t); "
        "seconds are training wall time, with runs sharing the machine's cores. The rolling-return columns read "
        "every run's training curve at its end (equal episodes) and at the quickest run's training time (equal "
        "wall-clock). " + machines_sentence(summary),
        "",
        *markdown_header(header),
    ]
    for c in summary["configurations"]:
        cells = [c["name"], str(c["seeds"]), *(cell(c[play]["mean_team_return"], ".3f") for play in PLAYS)]
        cells += [cell(c["sampled"]["mean_episode_length"], ".2f"), cell(c["final_rolling_team_return"], ".3f")]
        cells += [cell(c["rolling_at_equal_wall"], ".3f"), cell(c["wall_s"], ",.1f")]
        lines.append(markdown_row(cells))
    lines += per_seed_markdown(
        summary,
        lambda _, run: " / ".join(f"{run[play]['mean_team_return']:.3f}" for play in PLAYS),
        "Team return of each run's final policy on the evaluation episodes: sampled / greedy / channel cut.",
    )
    lines += along_budget_markdown(summary, "team return", ".3f")
    return "\n".join(lines) + "\n"


def plot_curves(runs: list[Run], curves: dict[Path, EnvCurve], cfg: EnvCompareConfig, path: Path) -> None:
    """A line per technique: the rolling mean team return over seeds, its 95% interval shaded."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    for conf in dict.fromkeys(r.configuration for r in runs):
        seeds = [curves[r.folder] for r in runs if r.configuration == conf]
        draw_seed_band(ax, conf.technique, seeds, "return_rolling")
    ax.set_xlabel("environment episodes")
    ax.set_ylabel("mean team return (rolling)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{cfg.base.env}, K = {cfg.base.channel.bits}: mean and 95% interval over seeds", fontsize=9)
    save_figure(fig, path)


def run_env_compare(cfg: EnvCompareConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train what is missing, then write curves.csv, curves.png/.svg, table.md and summary.json; returns the summary."""
    runs = study_runs(plan(cfg), cfg, log)
    cfg.out.mkdir(parents=True, exist_ok=True)
    execute_all(runs, cfg, log, describe)
    curves = {r.folder: read_env_curve(r.folder) for r in runs}
    summary = summarize(cfg, runs, curves)
    write_curves_csv(runs, curves, [], cfg.out / "curves.csv", CURVE_COLUMNS)
    plot_curves(runs, curves, cfg, cfg.out / "curves.png")
    write_text_atomic(cfg.out / "table.md", table_markdown(summary))
    write_text_atomic(cfg.out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
