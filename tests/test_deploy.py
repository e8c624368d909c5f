"""`bitcomm deploy`: agents as processes over UDP on loopback reproduce the simulator without drops,
do worse with 30% of datagrams dropped, and no process outlives the run."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.deploy import DeployError, episode_set, place_episode, run_deploy
from bitcomm.deploy import agent as agent_module
from bitcomm.deploy import world as world_module
from bitcomm.deploy.agent import Inbox
from bitcomm.deploy.protocol import pack_datagram, unpack_datagram
from bitcomm.envs.core import GoalExchangeCore
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import ConfigError
from bitcomm.policies.evaluation import evaluate, run_first_episodes
from bitcomm.policies.reference import OraclePolicy
from bitcomm.policies.source import PolicySource

TINY = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
ORACLE = PolicySource("oracle")
EVAL_KEYS = {"episodes", "mean_episode_length", "ci95", "mean_team_return", "success_rate"}


def test_wire_format_round_trips() -> None:
    bits = np.array([1, 0, 1, 1, 0, 0, 0, 1, 1], dtype=np.uint8)
    d = unpack_datagram(pack_datagram(77, 3, 12, 5, 40, bits))
    assert d is not None and (d.run_id, d.sender, d.episode, d.step, d.seq) == (77, 3, 12, 5, 40)
    np.testing.assert_array_equal(d.bits, bits)
    assert unpack_datagram(b"junk") is None and unpack_datagram(b"XXXX" + bytes(30)) is None
    task = TaskConfig(EnvConfig(n_agents=3, observes=(2, 0, 1)), ChannelConfig(recipients=((2, 1), (0,), (1,))))
    assert TaskConfig.from_dict(json.loads(json.dumps(task.to_dict()))) == task


def test_an_agent_drops_datagrams_it_cannot_read() -> None:
    """Another run's datagram, one with another bit count and one from a sender the agent does not hear are
    counted as foreign; the message of its step still arrives, and nothing else is kept."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        rx.bind(("127.0.0.1", 0))
        inbox = Inbox(rx, run_id=7, bits=4, senders=[1])
        four = np.array([1, 0, 1, 1], dtype=np.uint8)
        for datagram in (
            pack_datagram(8, 1, 0, 0, 0, four),  # another run
            pack_datagram(7, 1, 0, 0, 0, np.ones(9, dtype=np.uint8)),  # 9 bits, not 4
            pack_datagram(7, 60000, 0, 0, 0, four),  # a sender it does not hear
            b"BCM1" + bytes(3),  # torn header
            pack_datagram(7, 1, 0, 0, 0, four),  # its message
        ):
            tx.sendto(datagram, rx.getsockname())
        got = inbox.take([1], episode=0, step=0, deadline=time.monotonic() + 2.0)
    np.testing.assert_array_equal(got[1], four)
    assert inbox.stats == {"received": 1, "late": 0, "duplicate": 0, "foreign": 4} and not inbox.messages


def test_reordered_duplicated_and_late_datagrams_each_count_once() -> None:
    """A radio may deliver step 1 before step 0, repeat a datagram, or deliver one after its step was played:
    each message is read at its own step, `received` counts messages (not copies), and nothing stale is kept."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        rx.bind(("127.0.0.1", 0))
        inbox = Inbox(rx, run_id=7, bits=4, senders=[1])
        step0, step1 = np.array([1, 0, 0, 1], dtype=np.uint8), np.array([0, 1, 1, 0], dtype=np.uint8)
        for datagram in (
            pack_datagram(7, 1, 0, 1, 1, step1),  # ahead of its predecessor
            pack_datagram(7, 1, 0, 0, 0, step0),
            pack_datagram(7, 1, 0, 0, 0, step0),  # a repeat
        ):
            tx.sendto(datagram, rx.getsockname())
        time.sleep(0.05)  # all three waiting, as after a burst
        got0 = inbox.take([1], episode=0, step=0, deadline=time.monotonic() + 2.0)
        tx.sendto(pack_datagram(7, 1, 0, 0, 0, step0), rx.getsockname())  # a third copy, after step 0 was played
        time.sleep(0.05)
        got1 = inbox.take([1], episode=0, step=1, deadline=time.monotonic() + 2.0)
    np.testing.assert_array_equal(got0[1], step0)
    np.testing.assert_array_equal(got1[1], step1)
    assert inbox.stats == {"received": 2, "late": 1, "duplicate": 1, "foreign": 0} and not inbox.messages


class _Flood:
    """A UDP socket with another datagram always waiting, as under a flood faster than the agent reads (for a few
    seconds only, so that an agent that would read on forever fails the test rather than hangs it)."""

    def __init__(self, datagram: bytes) -> None:
        self.datagram, self.ends = datagram, time.monotonic() + 5.0

    def settimeout(self, timeout: float) -> None:
        pass

    def recv(self, size: int) -> bytes:
        if time.monotonic() > self.ends:
            raise BlockingIOError
        return self.datagram


def test_a_flood_does_not_hold_an_agent_past_its_deadline() -> None:
    inbox = Inbox(_Flood(b"noise"), run_id=7, bits=4, senders=[1])  # type: ignore[arg-type]
    began = time.monotonic()
    got = inbox.take([1], episode=0, step=0, deadline=began + 0.05)
    assert time.monotonic() - began < 1.0
    assert got == {} and inbox.stats["foreign"] > 0 and inbox.stats["received"] == 0


@pytest.mark.parametrize("world", ["localhost", "127.0.0.1:http", "127.0.0.1:70000", ":5", "127.0.0.1:²"])
def test_an_agent_started_with_a_bad_world_address_says_so_in_one_line(
    world: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert agent_module.main(["--world", world, "--agent", "0"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and f"invalid world={world!r}" in err


@pytest.mark.parametrize(
    ("bad", "line"),
    [
        ({"episodes": 0}, r"invalid episodes=0: must be an integer >= 1"),  # numpy: "need at least one array"
        ({"seed": -1}, r"invalid seed=-1: must be an integer in \[0, 4294967295\]"),  # numpy: "non-negative integer"
        ({"deadline_ms": -5}, r"invalid deadline-ms=-5: must be a finite number > 0"),  # played on as 0
        ({"timeout_s": float("nan")}, r"invalid timeout=nan: must be a finite number > 0"),
    ],
)
def test_run_deploy_refuses_bad_values_in_one_line_before_any_process_starts(
    bad: dict[str, float], line: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As `bitcomm deploy`'s flags do, and as `evaluate` does for its episodes and seed."""
    monkeypatch.setattr(world_module.subprocess, "Popen", None)  # starting an agent would be a TypeError
    with pytest.raises(ConfigError, match=f"^{line}$"):
        run_deploy(ORACLE, TINY, **{"episodes": 2, **bad})  # type: ignore[arg-type]


@pytest.mark.parametrize("task", [TINY, TaskConfig(EnvConfig(size=5, n_agents=3, observes=(2, 0, 1)))])
def test_placed_episode_is_the_evaluators_episode(task: TaskConfig) -> None:
    starts, goals = episode_set(task, 20, seed=3)
    env = VecGoalExchange(task, 20, seed=np.random.SeedSequence(3).spawn(1)[0])
    core = GoalExchangeCore(task.env, 1, seed=0)
    for e in range(20):
        place_episode(core, starts[e], goals[e])
        np.testing.assert_array_equal(core.obs[0], env.core.obs[e])
        np.testing.assert_array_equal(core.state[0], env.core.state[e])
        assert core.t[0] == 0


def test_deploy_reproduces_the_simulator_without_drops() -> None:
    result = run_deploy(ORACLE, TINY, 60, seed=1, deadline_ms=50, timeout_s=60)
    simulated = evaluate(OraclePolicy(TINY), TINY, 60, seed=1)
    lo, hi = simulated.ci95
    assert lo <= result.summary.mean_episode_length <= hi and result.summary.success_rate == 1.0
    # the oracle is deterministic and no datagram is lost: the very same episodes, step for step
    lengths, _, _ = run_first_episodes(OraclePolicy(TINY), TINY, 60, 1)
    assert [o.length for o in result.outcomes] == lengths.tolist()
    assert result.network["missing"] == 0 and result.network["dropped"] == 0 and result.network["sent"] > 0


def test_dropped_datagrams_make_it_worse() -> None:
    lossy = TaskConfig(TINY.env, ChannelConfig(bits=4, drop_prob=0.3))
    result = run_deploy(ORACLE, lossy, 60, seed=1, deadline_ms=5, timeout_s=60)
    clean, _, _ = run_first_episodes(OraclePolicy(TINY), TINY, 60, 1)
    net = result.network
    assert result.summary.mean_episode_length > float(np.mean(clean))
    assert 0.2 < net["dropped"] / (net["sent"] + net["dropped"]) < 0.4
    assert net["missing"] > 0


FAILING_RADIO = """
import errno, socket
_sendto, _calls = socket.socket.sendto, [0]
def sendto(self, *args):
    _calls[0] += 1
    if self.type == socket.SOCK_DGRAM and _calls[0] % 3 == 0:
        raise OSError(errno.ENOBUFS, "No buffer space available")
    return _sendto(self, *args)
socket.socket.sendto = sendto
"""


def test_a_datagram_the_radio_fails_to_send_is_lost_not_fatal(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A radio's send can fail (no buffer space, the link down): the message is lost, as a dropped one is, and
    counted (`send_failed`); the run goes on."""
    (tmp_path / "sitecustomize.py").write_text(FAILING_RADIO)  # loaded by each agent process at start
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), *sys.path]))
    result = run_deploy(ORACLE, TINY, 20, seed=1, deadline_ms=5, timeout_s=60)
    net = result.network
    assert len(result.outcomes) == 20 and net["send_failed"] > 0 and net["sent"] > 0
    assert net["missing"] > 0  # read as zeros at the deadline


def test_actuation_noise_is_applied_by_the_world() -> None:
    shaky = TaskConfig(EnvConfig(size=4, act_fail_prob=0.4, act_delay=1), TINY.channel)
    result = run_deploy(ORACLE, shaky, 40, seed=2, deadline_ms=50, timeout_s=60)
    clean, _, _ = run_first_episodes(OraclePolicy(TINY), TINY, 40, 2)
    assert result.summary.mean_episode_length > float(np.mean(clean)) + 1.0


def test_cli_json_has_the_evaluators_keys() -> None:
    cmd = [sys.executable, "-m", "bitcomm.cli", "deploy", "--policy", "oracle", "--size", "4", "--bits", "4",
           "--episodes", "20", "--seed", "4", "--json", "--timeout", "60"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert EVAL_KEYS <= set(out) and EVAL_KEYS <= set(out["simulator"])
    assert out["mean_episode_length"] == out["simulator"]["mean_episode_length"]
    assert done.stderr.count("episode ") == 20


def test_a_run_past_its_time_bound_says_so() -> None:
    """Not "agent 0 did not answer within 10 s": every agent answered while the bound lasted."""
    played: list[int] = []
    with pytest.raises(DeployError, match=r"time bound \(--timeout\)") as stopped:
        run_deploy(
            ORACLE, TINY, 100_000, seed=0, deadline_ms=1, timeout_s=3, on_episode=lambda o: played.append(o.index)
        )
    assert [o.index for o in stopped.value.finished] == played == list(range(len(played)))


def test_the_cli_summarises_the_episodes_played_before_the_time_bound() -> None:
    cmd = [sys.executable, "-m", "bitcomm.cli", "deploy", "--policy", "oracle", "--size", "4", "--bits", "4",
           "--episodes", "100000", "--seed", "0", "--deadline-ms", "1", "--timeout", "8"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "time bound (--timeout)" in done.stderr and "Traceback" not in done.stderr
    lines = done.stdout.splitlines()
    finished = sum(line.startswith("episode ") for line in lines)
    assert finished > 0 and lines[-1].startswith(f"deployed, {finished} of 100000 episodes before it stopped: mean")


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_an_interrupted_run_summarises_the_episodes_it_played(signum: signal.Signals) -> None:
    """Ctrl-C (SIGINT to the terminal's process group) or `timeout` (SIGTERM to the group) printed "interrupted", or
    nothing at all, and lost the episodes played; now they are summarised as after the time bound, and the exit
    status says which signal stopped the run."""
    cmd = [sys.executable, "-m", "bitcomm.cli", "deploy", "--policy", "oracle", "--size", "4", "--bits", "4",
           "--episodes", "100000", "--seed", "0", "--deadline-ms", "1", "--timeout", "60"]  # fmt: skip
    world = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as in a terminal, even under CI
    )  # fmt: skip
    try:
        assert world.stdout is not None
        assert world.stdout.readline().startswith("episode 0:")
        os.killpg(world.pid, signum)  # the world and its agents, as a terminal or `timeout` signals them
        out, err = world.communicate(timeout=30)
    finally:
        if world.poll() is None:
            world.kill()
    assert world.returncode == 128 + signum and err.strip() == "bitcomm deploy: interrupted", err
    lines = ("episode 0: ...\n" + out).splitlines()
    finished = sum(line.startswith("episode ") for line in lines)
    assert lines[-1].startswith(f"deployed, {finished} of 100000 episodes before it stopped: mean episode length")


def test_an_agent_dying_ends_the_run(monkeypatch: pytest.MonkeyPatch) -> None:
    procs: list[subprocess.Popen[bytes]] = []
    real_popen = subprocess.Popen

    def recording_popen(*args: object, **kwargs: object) -> subprocess.Popen[bytes]:
        proc = real_popen(*args, **kwargs)  # type: ignore[call-overload]
        procs.append(proc)
        return proc  # type: ignore[no-any-return]

    monkeypatch.setattr(world_module.subprocess, "Popen", recording_popen)
    began = time.monotonic()
    with pytest.raises(DeployError, match="agent 1"):
        run_deploy(ORACLE, TINY, 10_000, seed=0, timeout_s=60, on_episode=lambda o: o.index == 2 and procs[1].kill())
    assert time.monotonic() - began < 30
    assert len(procs) == 2 and all(p.poll() is not None for p in procs)


def test_an_agent_that_fails_says_why() -> None:
    """Its exit status and last line, not only that it closed its connection (it had not exited yet)."""
    with pytest.raises(DeployError, match=r"^agent 0 exited with status 2: .*cannot load RUN 'no/such/run'"):
        run_deploy(PolicySource("run", "no/such/run"), TINY, 2, seed=0, timeout_s=60)


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(x) for x in path.read_text().split()] if path.exists() else []


def _running(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc to find the agents")
def test_agents_end_when_the_world_dies() -> None:
    cmd = [sys.executable, "-m", "bitcomm.cli", "deploy", "--size", "4", "--bits", "4", "--episodes", "100000",
           "--timeout", "120"]  # fmt: skip
    world = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert world.stdout is not None
        assert world.stdout.readline().startswith("episode 0:")
        agents = _children(world.pid)
        assert len(agents) == 2
        os.kill(world.pid, signal.SIGKILL)
        world.wait()
        deadline = time.monotonic() + 10
        while any(_running(a) for a in agents) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(_running(a) for a in agents)
    finally:
        if world.poll() is None:
            world.kill()


def test_threads_flag_sets_torchs_threads_and_agents_get_one(
    threads, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--threads N` (as on eval) sets this process's torch threads (the simulator's comparison); each agent
    process starts with OMP_NUM_THREADS=1 whatever the caller's environment says, which is left as it was; 0 is one
    error line."""
    from bitcomm.cli import main

    agent_threads: list[str | None] = []
    real_popen = subprocess.Popen

    def recording_popen(*args: object, **kwargs: object) -> subprocess.Popen[bytes]:
        env = kwargs.get("env") or os.environ
        agent_threads.append(env.get("OMP_NUM_THREADS"))  # type: ignore[attr-defined]
        return real_popen(*args, **kwargs)  # type: ignore[call-overload,no-any-return]

    monkeypatch.setattr(world_module.subprocess, "Popen", recording_popen)
    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    argv = ["deploy", "--policy", "oracle", "--size", "4", "--bits", "4", "--episodes", "3", "--json"]
    assert main([*argv, "--timeout", "60", "--threads", str(threads.want)]) == 0
    assert threads.calls == [threads.want]
    assert agent_threads == ["1", "1"] and os.environ["OMP_NUM_THREADS"] == "4"
    assert json.loads(capsys.readouterr().out)["episodes"] == 3
    assert threads.zero_is_one_line("deploy", capsys)
