"""The stop signals a trainer takes, and the processes it starts, which leave them to it.

Ctrl-C reaches the whole process group, and so does `timeout`'s SIGTERM (a scheduler's time limit reaches every
process of the job). A trainer takes them (`bitcomm.learn.run_folder.stop_after_batch`): it stops after its batch,
saves and exits. The processes it starts must not die of them first, or the batch they were on, and with it the
run's last minutes, would be lost: they start deaf to them (`deaf_children`) and, where they run bitcomm's code,
ignore them for good (`ignore_stop_signals`); the trainer stops them itself once it has saved.

A command that does not train (a study, a deployment) takes SIGTERM as Ctrl-C (`sigterm_interrupts`), so that what
it does on an interrupt (stop its runs, summarise the episodes played) it does when `kill PID` or a scheduler's time
limit stops it too.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""What `bitcomm.learn.run_folder.stop_after_batch` takes in a trainer."""

REPEAT_S = 0.5
"""A stop signal repeated sooner than this is the first one again: `timeout` signals its command, then the
command's process group, which holds the command too; a loaded machine can run the handler in between."""


class Stopped(KeyboardInterrupt):
    """A command stopped on a signal (a trainer once it has saved the batch it was on); `exit_code` is the shell's
    128 + signal, which `bitcomm.cli` exits with. A trainer's carries the checkpoint it saved and the episodes in it,
    so that a notebook or a script that caught it can resume or evaluate without reading the printed line."""

    def __init__(self, signum: int, checkpoint: Path | None = None, episodes: int | None = None) -> None:
        super().__init__(signal.Signals(signum).name)
        self.exit_code = 128 + signum
        self.checkpoint = checkpoint
        self.episodes = episodes

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled as what it was made of: a study's run sends its `Stopped` back to the study, and rebuilt from its
        message (the signal's name) it failed there, which broke the pool: every other run was ended at once,
        whether or not it had saved the batch it was on."""
        return type(self), (self.exit_code - 128, self.checkpoint, self.episodes)


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM (`kill PID`, a scheduler's time limit) raises `Stopped` as Ctrl-C raises KeyboardInterrupt, rather than
    ending the process at once; the command then exits 143, as killed by it. Where SIGTERM is not the default's (a
    caller took it) or off the main thread, nothing changes."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return

    def stop(signum: int, frame: object) -> None:
        raise Stopped(signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


@contextlib.contextmanager
def repeats_count_once() -> Iterator[None]:
    """Inside, the first stop signal goes to its handler (`Stopped`, KeyboardInterrupt) and the same or the other one
    within `REPEAT_S` of it is dropped, as that one again; one later goes to its handler too (a second Ctrl-C: stop
    at once). Installed before the first signal can come, so that the group's copy cannot land while the first
    one's clean-up (a study stopping its runs, a deployment's summary) has yet to begin: it did, now and then, and
    cut that clean-up short. Only stop signals that a Python handler has, and only in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    taken = {s: h for s in STOP_SIGNALS if callable(h := signal.getsignal(s))}
    first: list[float] = []

    def once(signum: int, frame: Any) -> None:
        now = time.monotonic()
        if first and now - first[0] < REPEAT_S:
            return
        first[:] = first or [now]
        taken[signal.Signals(signum)](signum, frame)

    for s in taken:
        signal.signal(s, once)
    try:
        yield
    finally:
        for s, handler in taken.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def held() -> Iterator[list[int]]:
    """Inside, a stop signal waits for the block to end, then goes to its handler; yields the signals waiting. For a
    save that must be whole: a second Ctrl-C while a stop's checkpoint was saved stopped the run before its plot was
    drawn, so learning_curve.png showed less than the checkpoint held. A block that ends in a stop
    (KeyboardInterrupt, `Stopped`) drops them: the stop they ask for is under way. Only stop signals that a Python
    handler has (a default one still ends the process at once), and only in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield []
        return
    taken = {s: h for s in STOP_SIGNALS if callable(h := signal.getsignal(s))}
    waiting: list[int] = []

    def wait(signum: int, frame: Any) -> None:
        waiting.append(signum)

    for s in taken:
        signal.signal(s, wait)
    try:
        yield waiting
    except KeyboardInterrupt:
        waiting.clear()
        raise
    finally:
        for s, handler in taken.items():
            signal.signal(s, handler)
        for signum in waiting:
            signal.raise_signal(signum)


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
