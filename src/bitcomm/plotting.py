"""What every bitcomm figure shares: written as PNG and SVG, atomically, byte for byte reproducible.

Figures are built on `matplotlib.figure.Figure` (no pyplot, so no global backend state); the SVG carries
no date and fixed element ids, so drawing the same data twice writes the same files.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

from bitcomm.files import write_atomic

FORMATS = ("png", "svg")


def log_scale_suits(values: Any) -> bool:
    """A log axis when the values span more than 20x (an oracle at 9 steps next to random play at 250)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return v.size > 0 and v.min() > 0 and v.max() / v.min() > 20


def save_figure(fig: Any, path: str | Path, formats: tuple[str, ...] = FORMATS, dpi: int = 100) -> list[Path]:
    """`fig` as `path` with each suffix in `formats` (PNG first); returns the paths written."""
    import matplotlib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    written = []
    with matplotlib.rc_context({"svg.hashsalt": "bitcomm"}):
        for fmt in formats:
            target = path.with_suffix(f".{fmt}")
            metadata = {"Date": None} if fmt == "svg" else None
            write_atomic(target, functools.partial(fig.savefig, dpi=dpi, format=fmt, metadata=metadata))
            written.append(target)
    return written
