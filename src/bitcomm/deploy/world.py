"""The world process of the deploy runtime: it stands in for the robots and their positioning system.

It holds the grid core (and with it the actuation noise `act_fail_prob`/`act_delay`), starts one
process per agent (`python -m bitcomm.deploy.agent`), and steps the episodes in lockstep: each step it
tells every agent its observation planes and the step index over TCP, collects their moves, and
applies them. It never carries a message: agents exchange those among themselves over UDP.

Episodes are those of `bitcomm.policies.evaluation.evaluate` with the same seed (the same starts and goals), so
the deployed policy and the simulated one face the same episode set. Actuation noise draws differ
(the world steps one episode at a time), and so do the channel's.

Every process ends when the run ends or when any of them dies: agents exit when the world's
connection closes; the world stops and kills the agents when one of them closes its connection,
exits or stays silent past the step timeout; everything is bounded by `timeout_s`. A control line that
is malformed (not JSON, not an object, a hello without the run's token, a reply of the wrong type or
with wrong fields) is ignored and counted (`DeployResult.network["control_malformed"]`), never fatal.
"""

from __future__ import annotations

import os
import secrets
import select
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO, Any, TypeGuard

import numpy as np

from bitcomm.config import TaskConfig, check_evaluation
from bitcomm.deploy.protocol import LineSocket, Malformed, PeerGone, encode_array
from bitcomm.envs.core import N_MOVES, GoalExchangeCore
from bitcomm.errors import check_number
from bitcomm.policies.evaluation import EvalResult, seeded_episode_envs
from bitcomm.policies.source import PolicySource


class DeployError(RuntimeError):
    """The run could not go on (an agent died, hung, or the time bound passed); one line."""

    finished: list[EpisodeOutcome]
    """The episodes played to their end before the run stopped (`run_deploy` fills it in)."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.finished = []


@dataclass(frozen=True)
class EpisodeOutcome:
    index: int
    length: int
    team_return: float
    success: bool
    wall_s: float


@dataclass(frozen=True)
class DeployResult:
    outcomes: list[EpisodeOutcome]
    max_steps: int
    """The task's episode cap, the longest an outcome can last (the summary's interval stays within it)."""
    network: dict[str, int] = field(default_factory=dict)
    """Datagram counts summed over agents: sent, dropped (on purpose), send_failed (refused by the system: lost),
    received, missing (at the deadline), late (after their step was played), duplicate (repeats of a message held),
    foreign (not this run's or unreadable); and `control_malformed`, the control lines the world ignored."""
    startup_s: float = 0.0
    wall_s: float = 0.0

    @property
    def summary(self) -> EvalResult:
        return EvalResult.from_episodes(
            np.array([o.length for o in self.outcomes]),
            np.array([o.team_return for o in self.outcomes]),
            np.array([o.success for o in self.outcomes]),
            self.max_steps,
        )


def episode_set(task: TaskConfig, episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`(E, n)` starts and goals of the first episodes `evaluate(..., episodes, seed)` plays."""
    envs = [env for _, env in seeded_episode_envs(task, episodes, seed)]
    return np.concatenate([env.core.pos for env in envs]), np.concatenate([env.core.goal for env in envs])


def place_episode(core: GoalExchangeCore, start: np.ndarray, goal: np.ndarray) -> None:
    """Begin a fresh episode in slot 0 of `core` from the given start and goal cells."""
    core.reset()
    core.begin(np.zeros(1, dtype=np.int64), start[None], goal[None])


EXIT_WAIT_S = 3.0
"""How long an agent that closed its connection is given to exit, so that the error names its status and last line."""

Fits = Callable[[dict[str, Any]], bool]
"""What a control reply must satisfy besides its type."""


class _Agents:
    """The agent processes and their control connections; `close` always leaves none running."""

    def __init__(self, n: int, end: float) -> None:
        self.n, self.end = n, end
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.token = secrets.token_hex(8)
        port = self.listener.getsockname()[1]
        self.logs: list[IO[bytes]] = []
        self.procs: list[subprocess.Popen[bytes]] = []
        # one torch thread an agent: it acts on one observation at a time, and the agents already take a core each
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        for i in range(n):
            log = tempfile.TemporaryFile()
            self.logs.append(log)
            cmd = [sys.executable, "-m", "bitcomm.deploy.agent", "--world", f"127.0.0.1:{port}", "--agent", str(i)]
            self.procs.append(
                subprocess.Popen(
                    [*cmd, "--token", self.token], stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env
                )
            )
        self.conns: list[LineSocket | None] = [None] * n
        self.udp_ports = [0] * n
        self.malformed = 0
        """Control lines ignored: not JSON objects, hellos that are not our agents', replies that do not fit."""

    def log_tail(self, i: int) -> str:
        self.logs[i].seek(0)
        lines = [x for x in self.logs[i].read().decode(errors="replace").splitlines() if x.strip()]
        return lines[-1].strip() if lines else "no output"

    def check_alive(self) -> None:
        for i, proc in enumerate(self.procs):
            code = proc.poll()
            if code is not None:
                raise DeployError(f"agent {i} exited with status {code}: {self.log_tail(i)}")

    def deadline(self, within: float) -> float:
        now = time.monotonic()
        if now >= self.end:
            raise DeployError("the run passed its time bound (--timeout)")
        return min(self.end, now + within)

    def accept(self, within: float = 60.0) -> None:
        """Wait for every agent's hello (index, token, UDP port)."""
        deadline = self.deadline(within)
        while any(c is None for c in self.conns):
            self.check_alive()
            if time.monotonic() > deadline:
                raise DeployError("agents did not connect in time")
            ready, _, _ = select.select([self.listener], [], [], 0.2)
            if not ready:
                continue
            sock, _ = self.listener.accept()
            conn = LineSocket(sock)
            try:
                hello = conn.recv(self.deadline(10.0))
            except (TimeoutError, PeerGone):
                conn.close()
                continue
            except Malformed:
                hello = {}
            i, port = hello.get("agent"), hello.get("udp_port")
            if hello.get("token") == self.token and _index(i, self.n) and _index(port, 65536) and not self.conns[i]:
                self.conns[i], self.udp_ports[i] = conn, port
            else:
                self.malformed += 1
                conn.close()  # not one of ours

    def gone(self, i: int) -> DeployError:
        """Agent i closed its connection: it is most likely exiting (on an error it printed), so its status and
        last line, which say why, are waited for a moment (an agent that loaded torch takes a second to exit)."""
        try:
            self.procs[i].wait(timeout=max(0.0, min(EXIT_WAIT_S, self.end - time.monotonic())))
        except subprocess.TimeoutExpired:
            pass
        self.check_alive()
        return DeployError(f"agent {i} closed its connection")

    def send(self, i: int, obj: dict[str, Any]) -> None:
        try:
            self._conn(i).send(obj)
        except PeerGone:
            raise self.gone(i) from None

    def recv(self, i: int, within: float, kind: str, fits: Fits | None = None) -> dict[str, Any]:
        """The next line from agent i of type `kind` (and that `fits`); other lines are ignored and counted."""
        deadline = self.deadline(within)
        while True:
            try:
                msg = self._conn(i).recv(deadline)
            except Malformed:
                self.malformed += 1
                continue
            except PeerGone:
                raise self.gone(i) from None
            except TimeoutError:
                self.check_alive()
                self.deadline(0.0)  # the wait was cut by the run's time bound: say that, not that the agent hung
                ignored = f" ({self.malformed} malformed control lines ignored)" if self.malformed else ""
                raise DeployError(f"agent {i} did not answer within {within:g} s{ignored}") from None
            if msg.get("type") == kind and (fits is None or fits(msg)):
                return msg
            self.malformed += 1

    def _conn(self, i: int) -> LineSocket:
        conn = self.conns[i]
        assert conn is not None
        return conn

    def close(self) -> None:
        for conn in self.conns:
            if conn is not None:
                conn.close()
        self.listener.close()
        for proc in self.procs:
            try:
                proc.wait(timeout=max(0.0, min(3.0, self.end + 3.0 - time.monotonic())))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for log in self.logs:
            log.close()


def _index(value: object, n: int) -> TypeGuard[int]:
    """An int (not a bool) in 0..n-1."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < n


def _move_of(episode: int, t: int) -> Fits:
    """A move reply for this episode and step, with a move in 0..N_MOVES-1."""
    return lambda m: m.get("episode") == episode and m.get("t") == t and _index(m.get("move"), N_MOVES)


def _counts(msg: dict[str, Any]) -> bool:
    """A stats reply: every count a non-negative int."""
    return all(_index(v, 1 << 62) for k, v in msg.items() if k not in ("type", "agent"))


def run_deploy(
    source: PolicySource,
    task: TaskConfig,
    episodes: int,
    seed: int = 0,
    deadline_ms: float = 20.0,
    timeout_s: float = 300.0,
    step_timeout_s: float = 10.0,
    on_episode: Callable[[EpisodeOutcome], None] | None = None,
) -> DeployResult:
    """Play `episodes` episodes with one process per agent exchanging messages over UDP on loopback.

    `task.channel.drop_prob` and `flip_prob` act on the wire: each sender drops a datagram with
    `drop_prob` (independently per recipient) and flips each bit with `flip_prob`, from its own seeded
    stream. `deadline_ms`: how long after it learns its step an agent waits for that step's messages.
    """
    check_evaluation(episodes, seed)  # numpy's "need at least one array to concatenate" for no episodes
    for name, value in (("deadline_ms", deadline_ms), ("timeout", timeout_s), ("step_timeout_s", step_timeout_s)):
        check_number(name, value, 0.0, strict=True)  # a negative deadline played on, as if it were 0
    began = time.monotonic()
    n = task.env.n_agents
    starts, goals = episode_set(task, episodes, seed)
    agents = _Agents(n, began + timeout_s)
    outcomes: list[EpisodeOutcome] = []
    try:
        agents.accept()
        run_id = secrets.randbits(32)
        slot_senders = task.slot_senders
        for i in range(n):
            agents.send(i, {
                "type": "config", "task": task.to_dict(), "policy": source.to_dict(), "seed": seed,
                "run_id": run_id, "deadline_ms": deadline_ms, "time_left_s": agents.end - time.monotonic() + 2.0,
                "flip_prob": task.channel.flip_prob, "drop_prob": task.channel.drop_prob,
                "peers": [agents.udp_ports[x] for x in task.recipient_lists[i]],
                "slot_senders": slot_senders[i].tolist(),
            })  # fmt: skip
        for i in range(n):
            agents.recv(i, 120.0, "ready")  # building a policy may load a network
        startup = time.monotonic() - began

        core = GoalExchangeCore(task.env, 1, seed=np.random.SeedSequence(seed, spawn_key=(n,)))
        for e in range(episodes):
            place_episode(core, starts[e], goals[e])
            t0 = time.perf_counter()
            while True:
                t = int(core.t[0])
                for i in range(n):
                    agents.send(i, {"type": "step", "episode": e, "t": t, "planes": encode_array(core.obs[0, i])})
                moves = np.zeros((1, n), dtype=np.int64)
                fits = _move_of(e, t)
                for i in range(n):
                    moves[0, i] = agents.recv(i, step_timeout_s, "move", fits)["move"]
                fin = core.step(moves).finished
                if fin.env_index.size:
                    outcome = EpisodeOutcome(
                        e, int(fin.length[0]), float(fin.team_return[0]), bool(fin.success[0]), time.perf_counter() - t0
                    )
                    outcomes.append(outcome)
                    if on_episode is not None:
                        on_episode(outcome)
                    break

        network: dict[str, int] = {}
        for i in range(n):
            agents.send(i, {"type": "stop"})
        for i in range(n):
            stats = agents.recv(i, 10.0, "stats", _counts)
            for key, value in stats.items():
                if key not in ("type", "agent"):
                    network[key] = network.get(key, 0) + int(value)
        network["control_malformed"] = agents.malformed
        return DeployResult(outcomes, task.env.max_steps, network, startup, time.monotonic() - began)
    except DeployError as err:
        err.finished = outcomes  # what was played still counts: the command summarises it
        raise
    finally:
        agents.close()
