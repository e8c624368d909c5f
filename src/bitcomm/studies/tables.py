"""Writing a study's rows as CSV: one function for every command that reports a table."""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path


def write_rows_csv(rows: Iterable[Mapping[str, object]], fieldnames: Sequence[str], path: str | Path) -> Path:
    """Write `rows` under a header of `fieldnames` to `path` (creating its folder); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(fieldnames))
        writer.writeheader()
        writer.writerows(rows)
    return path
