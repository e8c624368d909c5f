"""Where loose runs' learning curves stand: what `bitcomm compare` reads off its own run folders, for runs
trained one by one with `bitcomm train` (the 32x32 study's later seeds, docs/results.md 3f).

Per run: the rolling training episode length (`charts/episode_length_rolling` of metrics.csv) at each episode
mark, interpolated between logged batches as the study's tables are, and the episodes and training seconds
after which it first fell below 2x and 1.15x the oracle. The oracle is played on the study's evaluation set
(`--eval-episodes` episodes of `--eval-seed`, 1,000 of seed 1000 as in `bitcomm compare`) for each task the
runs were trained on. Then, per technique (estimator + message head) and task, the mean and 95% interval over
the runs given (Student's t, `bitcomm.stats`) at each mark (of the runs that played that far), and how
many runs reached each level.
And per run, where its metrics.csv logs the marginal message entropy (a recipe with the marginal bonus, the
default's), how much its messages say about what the senders see: `charts/entropy_message_marginal` (the entropy of
a batch's average message distribution) minus `charts/entropy_message` (the average per-message entropy), a batch
estimate of I(sender's observation; message) in nats, averaged over the logged batches within `--window` episodes of
each mark (docs/results.md 3f reads it).
The last line printed is one JSON object.

    python benchmarks/run_marks.py runs/s30-32x32-improved-onehot-seed3 runs/s30-32x32-improved-onehot-seed4 \\
        --marks 25000,50000,100000,150000,200000
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

MARKS = (25_000, 50_000, 100_000, 150_000, 200_000)
WINDOW = 2_000
"""Episodes either side of a mark whose logged batches the message information is averaged over."""
INFORMATION = ("entropy_message_marginal", "entropy_message")


def parse_marks(text: str) -> tuple[int, ...]:
    """'25000,50000' -> (25000, 50000); one error line for anything but positive integers."""
    try:
        marks = tuple(int(x) for x in text.split(","))
    except ValueError:
        marks = ()
    if not marks or min(marks) < 1:
        raise argparse.ArgumentTypeError(f"invalid marks={text!r}: must be positive integers joined by commas")
    return marks


def rolling_at_marks(curve: Any, marks: tuple[int, ...]) -> dict[int, float | None]:
    """The curve's rolling length at each mark, interpolated between logged batches; None past its last one."""
    from bitcomm.studies.compare import rolling_at_episodes

    return {m: rolling_at_episodes(curve, m, "length_rolling") if m <= curve.episodes[-1] else None for m in marks}


def information_at_marks(folder: Path, marks: tuple[int, ...], window: int) -> dict[int, float | None] | None:
    """The batch estimate of I(sender's observation; message) in nats at each mark (None past the run's last batch,
    as for its rolling length, or where no batch was logged within `window` episodes of it); None for a run whose
    metrics.csv does not log the marginal message entropy."""
    from bitcomm.studies.compare import read_columns

    with (folder / "metrics.csv").open(newline="") as f:
        header = next(csv.reader(f), [])
    if not all(f"charts/{c}" in header for c in INFORMATION):
        return None
    episodes, _, marginal, per_message = read_columns(folder, INFORMATION)
    information = marginal - per_message

    def at(mark: int) -> float | None:
        near = np.abs(episodes - mark) <= window
        return float(information[near].mean()) if mark <= episodes[-1] and near.any() else None

    return {m: at(m) for m in marks}


def run_marks(folder: Path, oracle: float | None, marks: tuple[int, ...], window: int = WINDOW) -> dict[str, Any]:
    """One run's rolling length at the marks, its first crossings of the study's levels, and its message
    information at the marks."""
    from bitcomm.studies.compare import THRESHOLDS, first_below, read_curve, threshold_key

    curve = read_curve(folder)
    return {
        "run": str(folder),
        "episodes": int(curve.episodes[-1]),
        "wall_s": float(curve.wall_s[-1]),
        "rolling_at": rolling_at_marks(curve, marks),
        "reached": {threshold_key(t): None if oracle is None else first_below(curve, t * oracle) for t in THRESHOLDS},
        "information_at": information_at_marks(folder, marks, window),
    }


def technique_of(folder: Path) -> tuple[str, Any]:
    """The run's technique ('improved + bitwise') and the task it trained on (its recorded config)."""
    from bitcomm.learn.config import TrainConfig
    from bitcomm.studies.compare import recorded_config

    cfg = recorded_config(folder, TrainConfig)
    return f"{cfg.estimator} + {cfg.model.messages}", cfg.task


def task_phrase(task: Any) -> str:
    """'32x32, 10 bits', and any task option set away from its default ('channel.flip_prob=0.05')."""
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig

    plain = TaskConfig(EnvConfig(size=task.env.size), ChannelConfig(bits=task.channel.bits)).to_dict()
    given = task.to_dict()
    changed = [f"{part}.{k}={v}" for part in given for k, v in given[part].items() if plain[part].get(k) != v]
    return ", ".join([f"{task.env.size}x{task.env.size}", f"{task.channel.bits} bits", *changed])


def summarize(rows: list[dict[str, Any]], marks: tuple[int, ...]) -> dict[str, Any]:
    """Mean and 95% interval over the runs at each mark; how many reached each level."""
    from bitcomm.studies.compare import THRESHOLDS, interval, threshold_key

    out: dict[str, Any] = {"runs": len(rows)}
    played = {m: [r["rolling_at"][m] for r in rows if r["rolling_at"][m] is not None] for m in marks}
    out["rolling_at"] = {m: interval(values) for m, values in played.items()}
    informed = [r["information_at"] for r in rows if r["information_at"] is not None]
    out["information_at"] = {m: interval([i[m] for i in informed if i[m] is not None]) for m in marks}
    for t in THRESHOLDS:
        key = threshold_key(t)
        hits = [r["reached"][key] for r in rows if r["reached"][key] is not None]
        out[key] = {"reached": len(hits), "episodes": interval([h["episodes"] for h in hits])}
    return out


def _interval_cell(value: dict[str, Any] | None, runs: int, fmt: str = ".2f") -> str:
    """'41.47 ± 5.37', with how many runs it is over where that is fewer than the group's ('41.47 (1 run)': one
    run has no interval)."""
    from bitcomm.studies.compare import cell, plural

    if value is None:
        return "-"
    over = f" ({plural(value['n'], 'run', 'runs')})" if value["n"] < runs else ""
    return f"{cell(value, fmt)}{over}"


def reached_cell(reached: dict[str, Any] | None) -> str:
    """When a level was first reached ('12,288 ep / 41 s'), or 'not reached'."""
    return f"{reached['episodes']:,} ep / {reached['wall_s']:.0f} s" if reached else "not reached"


def print_tables(groups: dict[str, dict[str, Any]], marks: tuple[int, ...]) -> None:
    from bitcomm.studies.compare import THRESHOLDS, threshold_key

    levels = [threshold_key(t) for t in THRESHOLDS]
    header = ["run", *(f"rolling at {m:,}" for m in marks), *(f"{k} the oracle" for k in levels), "trained"]
    for name, group in groups.items():
        oracle = group["oracle"]
        print(f"\n{name}: oracle {'cannot play' if oracle is None else f'{oracle:.2f}'} on the evaluation set")
        print("| " + " | ".join(header) + " |")
        print("|" + " --- |" * len(header))
        for r in group["per_run"]:
            cells = [r["run"], *("-" if r["rolling_at"][m] is None else f"{r['rolling_at'][m]:.2f}" for m in marks)]
            cells += [reached_cell(r["reached"][k]) for k in levels]
            cells.append(f"{r['episodes']:,} ep / {r['wall_s']:.0f} s")
            print("| " + " | ".join(cells) + " |")
        s = group["summary"]
        cells = [f"mean ± 95% over {s['runs']}", *(_interval_cell(s["rolling_at"][m], s["runs"]) for m in marks)]
        for k in levels:
            episodes = _interval_cell(s[k]["episodes"], s[k]["reached"], ",.0f")
            cells.append(f"{s[k]['reached']} of {s['runs']}; {episodes} ep")
        print("| " + " | ".join([*cells, ""]) + " |")
        print_information(group, marks)


def print_information(group: dict[str, Any], marks: tuple[int, ...]) -> None:
    """The message information table of a group, for its runs that log it."""
    informed = [r for r in group["per_run"] if r["information_at"] is not None]
    if not informed:
        return
    print("\nI(observation; message), nats (marginal minus per-message entropy, batches near each mark)")
    print("| run | " + " | ".join(f"at {m:,}" for m in marks) + " |")
    print("|" + " --- |" * (len(marks) + 1))
    for r in informed:
        values = ("-" if r["information_at"][m] is None else f"{r['information_at'][m]:.2f}" for m in marks)
        print(f"| {r['run']} | " + " | ".join(values) + " |")
    s = group["summary"]["information_at"]
    print(
        f"| mean ± 95% over {len(informed)} | " + " | ".join(_interval_cell(s[m], len(informed)) for m in marks) + " |"
    )


def main() -> None:
    from bitcomm.errors import ConfigError, check_int
    from bitcomm.studies.compare import oracle_result

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (each with config.json and metrics.csv)")
    ap.add_argument("--marks", type=parse_marks, default=MARKS, help="episode marks, comma-separated")
    ap.add_argument("--eval-episodes", type=int, default=1000, help="the oracle's episodes (default %(default)s)")
    ap.add_argument("--eval-seed", type=int, default=1000, help="the oracle's episode seed (default %(default)s)")
    ap.add_argument(
        "--window", type=int, default=WINDOW, help="episodes either side of a mark for the message information"
    )
    a = ap.parse_args()
    groups: dict[str, dict[str, Any]] = defaultdict(lambda: {"per_run": []})
    oracles: dict[str, float | None] = {}
    try:  # bad input is one line, before anything is read
        check_int("eval_episodes", a.eval_episodes, 1)
        check_int("eval_seed", a.eval_seed, 0)
        check_int("window", a.window, 0)
        for folder in a.runs:
            if not (folder / "config.json").is_file() or not (folder / "metrics.csv").is_file():
                raise ConfigError(f"invalid run={str(folder)!r}: needs config.json and metrics.csv (a run folder)")
            technique, task = technique_of(folder)
            key = json.dumps(task.to_dict(), sort_keys=True)
            if key not in oracles:
                result = oracle_result(task, a.eval_episodes, a.eval_seed)
                oracles[key] = None if result is None else result.mean_episode_length
            name = f"{technique}, {task_phrase(task)}"
            groups[name]["oracle"] = oracles[key]
            groups[name]["per_run"].append(run_marks(folder, oracles[key], a.marks, a.window))
    except ConfigError as err:
        ap.error(str(err))
    for group in groups.values():
        group["summary"] = summarize(group["per_run"], a.marks)
    print_tables(groups, a.marks)
    print(json.dumps({"marks": a.marks, "eval_episodes": a.eval_episodes, "eval_seed": a.eval_seed, "window": a.window,
                      **groups}))  # fmt: skip


if __name__ == "__main__":
    main()
