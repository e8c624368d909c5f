"""Writing a study's rows as CSV, and the words its tables and figures name the task by: one function each for every
command that reports a table."""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from bitcomm.files import write_atomic

if TYPE_CHECKING:
    from bitcomm.config import TaskConfig


def write_rows_csv(rows: Iterable[Mapping[str, object]], fieldnames: Sequence[str], path: str | Path) -> Path:
    """Write `rows` under a header of `fieldnames` to `path` (creating its folder), whole or not at all (a study
    stopped as it wrote left half a table); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(fieldnames))
            writer.writeheader()
            writer.writerows(rows)

    write_atomic(path, write)
    return path


def task_title(task: TaskConfig, varied: Iterable[str] = ()) -> str:
    """A title's words for `task`: its grid, agents, K, delay and channel noise, less the `varied` options (flag names)
    that a panel's title names. (Titles named the grid and K alone: a 3-agent study with flips read as the paper's
    task, one varying bits=3,4 was titled "K = 7" above both panels, a run whose messages are all dropped as one
    that talks.)"""
    env, channel = task.env, task.channel
    words = {
        "size": f"{env.size}x{env.size} grid",
        "agents": f"{env.n_agents} agents",
        "bits": f"K = {channel.bits}",
        "delay": f"delay {channel.delay}",
        "flip_prob": f"flip {channel.flip_prob:g}",
        "drop_prob": f"drop {channel.drop_prob:g}",
    }
    return ", ".join(text for name, text in words.items() if name not in varied)
