"""An exclusive lock on a run folder, so that two writers never interleave their checkpoints and logs.

`fcntl.flock` on `<run>/.lock`: the kernel drops the lock when its holder's process ends, however it
ends, so a lock file left behind by a killed run blocks nothing. The holder writes its pid into the
file, for the one line that refuses a second writer. The lock is re-entrant within a process (a
comparison evaluates a run it has just trained); its file descriptor is not inherited by children.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from bitcomm.errors import ConfigError

LOCK = ".lock"
_held: dict[str, int] = {}
"""Real path of a run folder this process holds -> how many `run_lock` blocks hold it."""


def _refuse(run: Path, why: str) -> ConfigError:
    return ConfigError(f"invalid out={str(run)!r}: {why}")


def _holder(fd: int) -> str:
    text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    return text if text.isdigit() else "unknown"


@contextmanager
def run_lock(run: Path | str) -> Iterator[None]:
    """Hold `run`'s lock for the block, or stop with one line naming the pid that holds it."""
    import fcntl

    run = Path(run)
    key = os.path.realpath(run)
    if key in _held:
        _held[key] += 1
        try:
            yield
        finally:
            _held[key] -= 1
        return
    try:
        fd = os.open(run / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise _refuse(run, f"cannot create its lock file {LOCK} ({err.strerror or err})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = _holder(fd)
        os.close(fd)
        why = f"another process (pid {holder}) is writing this run folder; let it end or use another --out"
        raise _refuse(run, why) from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _held[key] = 1
        yield
    finally:
        _held.pop(key, None)
        os.ftruncate(fd, 0)
        os.close(fd)  # releases the lock
