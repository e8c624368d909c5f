"""Keep the memory one minibatch step frees for the next, instead of handing it back to the OS.

glibc's malloc serves a block above its mapping threshold with a fresh `mmap`, and gives the free space at
the top of its heap back to the OS once it passes the trim threshold; both thresholds follow the largest
block freed so far (up to 32 MiB and twice that). An update on a large task frees and reallocates tensors
of several MiB in every minibatch step (at 32x32 with a one-hot head, `(2048, 1024)` logits and their
gradients), so their pages go back to the OS and fault back in, zero-filled, on the next step: a quarter of
that update's time. Fixing the mapping threshold at its largest value (32 MiB) and the trim threshold at
1 GiB keeps those pages in the heap. It changes no result, only where memory comes from; a process's
resident size can stay up to the trim threshold above what it uses.

`benchmarks/allocator.py` measures what it is worth on a task (about nothing on the default 10x10, whose
tensors stay within the thresholds glibc adapts to). Set `BITCOMM_KEEP_FREED_MEMORY=0` to leave malloc alone.
"""

from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # mallopt parameters, <malloc.h>
MMAP_THRESHOLD = 32 << 20  # glibc's largest on 64-bit systems (HEAP_MAX_SIZE / 2)
TRIM_THRESHOLD = 1 << 30
ENV_VAR = "BITCOMM_KEEP_FREED_MEMORY"

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Fix glibc's thresholds (once per process, before training); returns whether they are set. A no-op
    off glibc (macOS, Windows, musl) or with `BITCOMM_KEEP_FREED_MEMORY=0`."""
    global _applied
    if _applied is None:
        _applied = False
        if os.environ.get(ENV_VAR, "1") != "0" and _is_glibc():
            try:
                libc = ctypes.CDLL("libc.so.6")
            except OSError:
                return False
            # the mapping threshold first: setting either turns off glibc's own adjustment of both
            _applied = bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
                libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)
            )
    return _applied


def _is_glibc() -> bool:
    try:
        return sys.platform.startswith("linux") and (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")
    except (ValueError, OSError, AttributeError):  # no such name here: not glibc
        return False
