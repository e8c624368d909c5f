"""How much memory the system can still give: what every check that refuses an oversize run reads (the
command line's up-front checks in `bitcomm.commands.flags`, and `bitcomm.learn.env_rollout.play` while a batch
of a wrapped env, whose episode length is not known in advance, is played), and what a one-hot policy holds while
it acts, which both count."""

from __future__ import annotations

import os
from pathlib import Path

BYTES_PER_GB = 1 << 30


def available_bytes() -> int:
    """Memory the system can still give (MemAvailable), or all of it where /proc is missing."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def acting_bytes(agents: int, bits: int, slots: int) -> int:
    """The float32 tables of 2^K a one-hot policy holds per episode at an acting step: per agent its logits,
    their softmax and cumulative sum, and one per slot it hears (`flags.play_bytes`, `--env`'s `check_env`, and
    `env_rollout.play` while it plays)."""
    return agents * (1 << bits) * (3 + slots) * 4
