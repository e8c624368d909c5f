"""`VecEnv`'s B copies split over W worker processes, for envs slow enough that stepping them one at a time
in the learner's process is what a batch waits on.

Each worker holds a `VecEnv` of its contiguous share of the copies (built with the same picklable maker), so
the per-copy work, dicts to arrays, is `VecEnv`'s own and the results are the same, bit for bit: copy b is
reset with seed b and stepped with row b of the actions wherever it lives. The pipes carry numpy arrays:
the seeds, actions and messages of a worker's rows out, the rows of `VecObservation` and `VecStep` back; the
workers step their shares at the same time. Workers start with `spawn` (no fork of a process holding torch
threads), ignore Ctrl-C and SIGTERM (`bitcomm.stop_signals`: the learner stops after its batch, saves it, and its
`close()` stops them), and exit when their pipe closes. A worker that
dies is one `WorkerDied` (a `ConfigError`) naming it and the env, never a hang; an exception raised in a worker
is raised here with the worker's traceback.
"""

from __future__ import annotations

import multiprocessing as mp
import time
import traceback
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, NamedTuple

import numpy as np
from pettingzoo import ParallelEnv

from bitcomm.envs.vector import EnvLayout, VecEnv, VecObservation, VecStep
from bitcomm.errors import ConfigError, bad_value, check_int
from bitcomm.stop_signals import deaf_children, ignore_stop_signals

CLOSE_SECONDS = 5.0
"""How long `close()` waits for a worker to close its copies before it kills it."""


class WorkerDied(ConfigError):
    """An env worker process ended (killed, or crashed inside the env's own code) while it had copies to step:
    the batch it was playing is lost, nothing else (a trainer saves what it had and says so)."""


class WorkerError(NamedTuple):
    """What a worker sends back instead of arrays when its envs raised."""

    config: bool
    """The error was a `ConfigError` (one line for the user), not a bug in the env."""
    text: str


def _work(conn: Connection, make: Callable[[], ParallelEnv], count: int) -> None:
    """A worker's loop: build a `VecEnv` of `count` copies, then answer `reset` and `step` until `close` or
    until the learner's end of the pipe is gone."""
    ignore_stop_signals()
    try:
        vec = VecEnv(make, count)
    except Exception as err:
        conn.send(WorkerError(isinstance(err, ConfigError), _describe(err)))
        conn.close()
        return
    try:
        conn.send(np.array(vec.num_envs))
        while True:
            try:
                command, *arrays = conn.recv()
            except EOFError:
                break
            if command == "close":
                break
            try:
                out = vec.reset(arrays[0]) if command == "reset" else vec.step(arrays[0], arrays[1])
                conn.send(_flat(out))
            except Exception as err:
                conn.send(WorkerError(isinstance(err, ConfigError), _describe(err)))
    except OSError:  # a reply could not be sent: the learner is gone
        pass
    finally:
        vec.close()
        conn.close()


def _describe(err: Exception) -> str:
    return str(err) if isinstance(err, ConfigError) else "".join(traceback.format_exception(err)).rstrip()


def _flat(out: VecObservation | VecStep) -> tuple[np.ndarray, ...]:
    """The arrays of a `VecObservation`, or of a `VecStep` (its observation's first)."""
    return (*out.next, *out[1:]) if isinstance(out, VecStep) else tuple(out)


def check_workers(workers: object, num_envs: int, least: int) -> None:
    """One line unless `workers` is an integer from `least` to `num_envs` (each worker steps a copy or more)."""
    check_int("env_workers", workers, least)
    if workers > num_envs:  # type: ignore[operator]
        raise bad_value("env-workers", workers, f"at most num-envs ({num_envs}): each worker steps a copy or more")


class SubprocVecEnv(VecEnv):
    """`VecEnv`'s interface (`layout`, `num_envs`, `running`, `reset`, `step`, `close`, `with`) over `workers`
    processes, each stepping a contiguous share of the `num_envs` copies. `make` must pickle (e.g.
    `bitcomm.envs.vector.WrappedEnvMaker`); `name` names the env in errors."""

    def __init__(self, make: Callable[[], ParallelEnv], num_envs: int, workers: int, name: str | None = None) -> None:
        check_int("num_envs", num_envs, 1)
        check_workers(workers, num_envs, 1)
        self.name = name or repr(make)
        probe = make()  # a bad env or channel is one line here, before any process starts
        try:
            self.layout = EnvLayout.of(probe)
        finally:
            probe.close()
        self.num_envs = num_envs
        self.running = np.zeros(num_envs, dtype=bool)
        self.envs = []  # the copies live in the workers
        edges = np.linspace(0, num_envs, workers + 1).round().astype(int)
        self.slices = [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
        ctx = mp.get_context("spawn")
        self.conns: list[Connection] = []
        self.procs: list[Any] = []
        try:
            for w, share in enumerate(self.slices):
                parent, child = ctx.Pipe()
                proc = ctx.Process(
                    target=_work, args=(child, make, share.stop - share.start), name=f"bitcomm-env-{w}", daemon=True
                )
                with deaf_children():  # till `_work` ignores them: a group's SIGTERM killed it mid-batch
                    proc.start()
                child.close()  # only the worker holds its end, so its death reads as EOF here
                self.conns.append(parent)
                self.procs.append(proc)
            for w in range(workers):
                self._receive(w)
        except BaseException:
            self.close()
            raise

    def reset(self, seeds: Sequence[int] | np.ndarray) -> VecObservation:
        seeds = np.asarray(seeds)
        for w, share in enumerate(self.slices):
            self._send(w, ("reset", seeds[share]))
        parts = [self._receive(w) for w in range(len(self.slices))]
        self.running[:] = True
        return VecObservation(*(np.concatenate(x) for x in zip(*parts, strict=True)))

    def step(self, actions: np.ndarray, messages: np.ndarray) -> VecStep:
        for w, share in enumerate(self.slices):
            self._send(w, ("step", actions[share], messages[share]))
        arrays = [np.concatenate(x) for x in zip(*(self._receive(w) for w in range(len(self.slices))), strict=True)]
        st = VecStep(VecObservation(*arrays[:4]), *arrays[4:])
        self.running &= ~st.ended
        return st

    def close(self) -> None:
        """Stop the workers (each closes its copies); safe to call twice, and after a worker died."""
        for conn in self.conns:
            try:
                conn.send(("close",))
            except OSError:
                pass
        for conn, proc in zip(self.conns, self.procs, strict=True):
            deadline = time.monotonic() + CLOSE_SECONDS
            while proc.is_alive() and time.monotonic() < deadline:
                try:
                    if conn.poll(0.05):
                        conn.recv()  # a reply left unread (another worker failed first): the worker can go on
                except (EOFError, OSError):
                    proc.join(0.05)
            if proc.is_alive():  # it ignores SIGTERM
                proc.kill()
            proc.join()
            conn.close()
        self.conns, self.procs = [], []

    def _send(self, w: int, message: tuple[Any, ...]) -> None:
        try:
            self.conns[w].send(message)
        except OSError:  # BrokenPipeError, ConnectionResetError: the worker is gone
            raise self._died(w) from None

    def _receive(self, w: int) -> Any:
        try:
            reply = self.conns[w].recv()
        except (EOFError, OSError):
            raise self._died(w) from None
        if isinstance(reply, WorkerError):
            where = f"env worker {w} of {len(self.slices)} ({self.name})"
            if reply.config:
                raise ConfigError(reply.text)
            raise RuntimeError(f"{where} raised:\n{reply.text}")
        return reply

    def _died(self, w: int) -> WorkerDied:
        proc = self.procs[w]
        proc.join(timeout=5)
        return WorkerDied(
            f"env worker {w} of {len(self.slices)} (pid {proc.pid}) running {self.name} died "
            f"(exit code {proc.exitcode}); --env-workers 0 steps the env in this process, where its own error shows"
        )
