"""The stop signals a trainer takes, and the processes it starts, which leave them to it.

Ctrl-C reaches the whole process group, and so does `timeout`'s SIGTERM (a scheduler's time limit reaches every
process of the job). A trainer takes them (`bitcomm.learn.run_folder.stop_after_batch`): it stops after its batch,
saves and exits. The processes it starts must not die of them first, or the batch they were on, and with it the
run's last minutes, would be lost: they start deaf to them (`deaf_children`) and, where they run bitcomm's code,
ignore them for good (`ignore_stop_signals`); the trainer stops them itself once it has saved.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""What `bitcomm.learn.run_folder.stop_after_batch` takes in a trainer."""


@contextlib.contextmanager
def deaf_children() -> Iterator[None]:
    """Processes started inside begin with `STOP_SIGNALS` blocked (a signal mask outlives fork and exec), so that a
    stop signal sent to the whole process group reaches the trainer alone: a worker of bitcomm's unblocks them once
    it ignores them (`ignore_stop_signals`); the servers of a private Ray instance keep them blocked until
    `ray.shutdown` kills them, where a group's SIGTERM ended them at once and the driver with them, unsaved, about
    one stop in three."""
    if not hasattr(signal, "pthread_sigmask"):  # Windows: no process groups to signal
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def ignore_stop_signals() -> None:
    """In a worker started by `deaf_children`: ignore `STOP_SIGNALS` (the trainer stops it, or kills it), then
    unblock them; a signal pending from the start is dropped."""
    for s in STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
