"""Text rendering of one goal-exchange episode (the PettingZoo view's `render_mode="ansi"`)."""

from __future__ import annotations

import numpy as np


def render_ansi(pos: np.ndarray, goal: np.ndarray, size: int) -> str:
    """A `size x size` text grid: agent i as the digit `i % 10`, its goal as the letter `a + i % 26`,
    `*` where several agents stand, `.` elsewhere. `pos` and `goal` are `(n,)` cell indices."""
    grid = [["."] * size for _ in range(size)]
    for i, cell in enumerate(np.asarray(goal).tolist()):
        grid[cell // size][cell % size] = chr(ord("a") + i % 26)
    standing = np.bincount(np.asarray(pos), minlength=size * size)
    for i, cell in enumerate(np.asarray(pos).tolist()):
        grid[cell // size][cell % size] = "*" if standing[cell] > 1 else str(i % 10)
    return "\n".join(" ".join(row) for row in grid)
