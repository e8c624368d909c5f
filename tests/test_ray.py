"""Training on Ray (issue 19) on a local two-CPU Ray instance and a tiny grid: synchronous runs are bit for bit
the same through a killed actor and a killed driver; asynchronous runs keep their staleness bound, count
the batches they drop and the actors they replace; runs move between Ray and the local trainer; bad flags
get one line."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig

ray = pytest.importorskip("ray")

STARTUP_S = 300
"""How long a run may take to write its first row or checkpoint: `make test` runs two test files at once, and a
loaded 2-core machine starts Ray and a driver slowly (over 60 s seen)."""
TINY = ["--size", "4", "--bits", "4", "--max-steps", "16", "--num-envs", "16", "--quiet", "--eval-episodes", "0"]


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    """A local Ray instance for the module; yields its address."""
    ray.init("local", num_cpus=2, include_dashboard=False, object_store_memory=80 * 2**20, log_to_driver=False)
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


def tiny_config(**kw: Any) -> Any:
    from bitcomm.learn.config import make_train_config

    task = TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=4))
    options = {"num_envs": 16, "episodes": 96, "checkpoint_seconds": 1e9, "backend": "ray", "workers": 2, **kw}
    return make_train_config("reinforced", task, **options)


def rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def learning(run: Path) -> list[dict[str, str]]:
    """The rows without timings and fault counts: what a reproducible run repeats."""
    return [{k: v for k, v in r.items() if k != "wall_s" and not k.startswith("ray/")} for r in rows(run)]


def weights(run: Path) -> dict[str, torch.Tensor]:
    from bitcomm.checkpoint import load_weights

    w, _ = load_weights(run)
    return {f"{p}.{k}": v for p, sd in w.items() for k, v in sd.items()}


def same_weights(a: Path, b: Path) -> bool:
    wa, wb = weights(a), weights(b)
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def kill_an_actor_after_a_row(run: Path) -> threading.Thread:
    """Kill one rollout actor, as a user would from outside, once the run has logged an update."""
    from bitcomm.learn.ray_backend import ACTOR_PREFIX

    before = len(rows(run)) if (run / "metrics.csv").is_file() else 0

    def kill() -> None:
        deadline = time.monotonic() + STARTUP_S
        while time.monotonic() < deadline and not ((run / "metrics.csv").is_file() and len(rows(run)) > before):
            time.sleep(0.01)
        names = [a["name"] for a in ray.util.list_named_actors(all_namespaces=True)]
        ray.kill(ray.get_actor(sorted(n for n in names if n.startswith(ACTOR_PREFIX))[0]))

    thread = threading.Thread(target=kill)
    thread.start()
    return thread


def test_sync_is_bit_for_bit_through_a_killed_actor_and_a_killed_driver(cluster: str, tmp_path: Path) -> None:
    from bitcomm.learn.run import train

    torch.set_num_threads(1)
    killer = kill_an_actor_after_a_row(tmp_path / "actor")
    train(tiny_config(), tmp_path / "actor", progress=False)
    killer.join()
    actor = rows(tmp_path / "actor")
    assert [int(r["batch"]) for r in actor] == [2, 4, 6]  # two actors' batches per update
    assert [int(r["episodes"]) for r in actor] == [32, 64, 96]
    assert {r["ray/staleness"] for r in actor} == {"0"} and actor[-1]["ray/restarts"] == "1"

    # the driver killed after its first checkpoint, the run resumed on the same cluster: the same run
    out = tmp_path / "driver"
    args = ["train", *TINY, "--episodes", "96", "--backend", "ray", "--workers", "2", "--checkpoint-seconds", "0"]
    # os.environ as it is now: the cluster's authentication mode, set by ray.init, must reach the driver
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", *args, "--address", cluster, "--out", str(out)],
        env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    latest = out / "checkpoints" / "latest.json"
    deadline = time.monotonic() + STARTUP_S
    while not latest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert int(rows(out)[-1]["episodes"]) < 96, "the run ended before it could be killed"
    assert main([*args, "--out", str(out), "--resume"]) == 0
    assert rows(out)[-1]["ray/restarts"] == "0"
    assert learning(out) == learning(tmp_path / "actor")
    assert same_weights(out, tmp_path / "actor")


def test_sigterm_stops_the_driver_after_its_batches_saved(cluster: str, tmp_path: Path) -> None:
    """`kill PID` or a scheduler's time limit: the batches in flight are used, the run saves them and exits 143
    (before, the handler `ray.init` installs ended it with status 15 and nothing saved since the last checkpoint)."""
    out = tmp_path / "run"
    args = ["train", *TINY, "--episodes", "96000", "--backend", "ray", "--workers", "2", "--checkpoint-seconds", "3600"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", *args, "--address", cluster, "--out", str(out)],
        env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + STARTUP_S
    while proc.poll() is None and time.monotonic() < deadline and not ((out / "metrics.csv").is_file() and rows(out)):
        time.sleep(0.02)  # an update logged: the run is in its loop
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM and "Traceback" not in err, err
    played = int(rows(out)[-1]["episodes"])
    assert (out / "checkpoints" / f"ckpt_{played:09d}.state.pt").is_file() and f"stopped after {played}" in err


def blocks_sigterm(pid: int) -> bool:
    """Whether process `pid` has SIGTERM blocked (Linux: /proc/PID/status)."""
    mask = next(line for line in Path(f"/proc/{pid}/status").read_text().splitlines() if line.startswith("SigBlk:"))
    return bool(int(mask.split()[1], 16) >> (signal.SIGTERM - 1) & 1)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_sigterm_to_the_process_group_stops_a_private_ray_instance_s_driver_saved(tmp_path: Path) -> None:
    """`timeout` (and a scheduler's time limit) signals every process of the group, which holds the servers of the
    Ray instance the driver starts without --address: they keep SIGTERM blocked, so the driver saves (before, they
    ended at the signal and, about one stop in three, took the driver with them before it saved: exit 1, "The
    connection to the plasma store is failed", nothing saved since the last checkpoint)."""
    import psutil

    out = tmp_path / "run"
    args = ["train", *TINY, "--episodes", "96000", "--backend", "ray", "--workers", "1", "--checkpoint-seconds", "3600"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}  # its own instance, not the module's
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", *args, "--out", str(out)], env={**env, "OMP_NUM_THREADS": "1"},
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + STARTUP_S
        while (
            proc.poll() is None and time.monotonic() < deadline and not ((out / "metrics.csv").is_file() and rows(out))
        ):
            time.sleep(0.02)  # an update logged: the run is in its loop, its Ray started
        group = [p.pid for p in psutil.Process(proc.pid).children(recursive=True) if os.getpgid(p.pid) == proc.pid]
        assert group and all(blocks_sigterm(pid) for pid in group)  # the actors, in groups of their own, are Ray's
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM and "Traceback" not in err, (proc.returncode, err)
    played = int(rows(out)[-1]["episodes"])
    assert (out / "checkpoints" / f"ckpt_{played:09d}.state.pt").is_file() and f"stopped after {played}" in err


def test_async_keeps_its_staleness_bound_and_runs_move_between_local_and_ray(cluster: str, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["train", *TINY, "--out", str(out), "--episodes", "32"]) == 0
    # local -> Ray, asynchronous, an actor killed
    killer = kill_an_actor_after_a_row(out)
    resume = ["train", *TINY, "--out", str(out), "--resume", "--backend", "ray", "--workers", "2", "--staleness", "1"]
    assert main([*resume, "--episodes", "192"]) == 0
    killer.join()
    r = rows(out)[2:]
    assert [int(x["batch"]) for x in r] == list(range(3, 13))  # one batch per update
    assert all(int(x["ray/staleness"]) <= 1 for x in r)
    # the replaced actor's batch was asked for while the other actor went on: too old when it came, dropped
    assert r[-1]["ray/restarts"] == "1" and int(r[-1]["ray/dropped"]) >= 1
    # Ray -> local: --resume without --backend continues in this process
    assert main(["train", *TINY, "--out", str(out), "--resume", "--episodes", "224"]) == 0
    assert [int(x["episodes"]) for x in rows(out)][-3:] == [192, 208, 224]


def test_a_rollout_actor_plays_the_greedy_senders_and_held_messages_of_its_batch_s_place_in_the_schedule() -> None:
    """Batch k of a run follows k full batches (`k * num_envs` episodes), so an actor knows from k alone how many
    of its episodes send the most likely message (`greedy_senders`) or one drawn word (`held_messages`), as the local
    trainer does, once the protocol has formed."""
    from bitcomm.learn.ray_backend import RolloutWorker

    cfg = tiny_config(
        episodes=1000,
        num_envs=8,
        greedy_senders=0.25,
        greedy_senders_from=0.5,
        held_messages=0.25,
        held_messages_from=0.5,
    )
    worker = RolloutWorker(cfg.to_dict())
    weights = {k: v.numpy() for k, v in worker.policy.state_dict().items()}
    before, after = (
        {k: v.copy() for k, v in worker.collect(weights, 0, batch)["rollout"].items()} for batch in (62, 63)
    )
    assert before["sent_greedy"].tolist() == [False] * 8 and after["sent_greedy"].tolist() == [True] * 2 + [False] * 6
    one_word = [
        bool((ro["bits"][ro["valid"][:, b], b] == ro["bits"][0, b]).all()) for ro in (before, after) for b in range(8)
    ]
    assert one_word == [False] * 8 + [True] * 4 + [False] * 4  # then the held messages' columns (`held_messages`)
    # `senders_wait_below`: the driver passes where the protocol formed (None: not yet); neither plays before
    for formed in (None, 0.9):
        assert not worker.collect(weights, 0, 63, formed)["rollout"]["sent_greedy"].any()


def test_joined_batches_keep_each_episode_and_pad_time_with_invalid_steps() -> None:
    import numpy as np

    from bitcomm.learn.ray_backend import RolloutWorker, join

    worker = RolloutWorker(tiny_config(num_envs=4).to_dict())
    weights = {k: v.numpy() for k, v in worker.policy.state_dict().items()}
    # copies: a worker's arrays are its buffers, which its next batch overwrites (Ray copies them when they leave)
    a, b = ({k: v.copy() for k, v in worker.collect(weights, 0, k)["rollout"].items()} for k in (0, 1))
    ro = join([a, b])
    Ta, Tb = a["valid"].shape[0], b["valid"].shape[0]
    assert ro.valid.shape == (max(Ta, Tb), 8) and np.array_equal(ro.length, np.concatenate([a["length"], b["length"]]))
    assert np.array_equal(ro.valid.sum(0).numpy(), ro.length)  # padding is invalid
    assert np.array_equal(ro.moves[:Ta, :4].numpy(), a["moves"])
    assert np.array_equal(ro.moves[:Tb, 4:].numpy(), b["moves"])
    assert np.array_equal(worker.collect(weights, 0, 1)["rollout"]["moves"], b["moves"])  # batch 1 is batch 1


def test_an_actor_that_cannot_start_stops_the_run_with_its_cause(cluster: str) -> None:
    from bitcomm.errors import ConfigError
    from bitcomm.learn.ray_backend import MAX_FAILURES, Actors

    class Broken:  # a node without bitcomm's dependencies, say
        def __init__(self, config: dict[str, Any]) -> None:
            import no_such_module  # noqa: F401

        def collect(self, *args: Any) -> None: ...

    actors = Actors(tiny_config(workers=1))
    ray.kill(actors.actors[0])
    actors.cls = ray.remote(num_cpus=1)(Broken)
    actors.launch(0, 0, None, 0)
    for _ in range(MAX_FAILURES - 1):
        assert actors.receive(None, 0) is None  # replaced, asked again
    with pytest.raises(ConfigError, match="died 3 times in a row .*No module named 'no_such_module'"):
        actors.receive(None, 0)
    assert actors.restarts == MAX_FAILURES - 1


def test_a_ray_runs_seconds_of_training_leave_out_its_actors_start(
    cluster: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`wall_s` is seconds of training over all the run's starts: a Ray run counted its actors' start (a process, its
    imports, its envs) as training, at every start, so a resumed run showed more than the same run uninterrupted.
    The actors here take `delay` s to start."""
    from bitcomm.learn import ray_backend
    from bitcomm.learn.run import train

    delay = 3.0

    class Slow(ray_backend.RolloutWorker):
        def __init__(self, config: dict[str, Any]) -> None:
            time.sleep(delay)
            super().__init__(config)

    monkeypatch.setattr(ray_backend, "RolloutWorker", Slow)
    out = tmp_path / "run"
    train(tiny_config(episodes=32), out, progress=False, address=cluster)
    first = rows(out)[0]  # one update on 2 batches of 16 episodes on 4x4, whose seconds a loaded machine stretches
    assert float(first["wall_s"]) - float(first["ray/update_s"]) < delay, first


def test_a_sigterm_while_a_private_instance_starts_stops_the_call_with_the_instance_shut_down(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """`timeout` firing while Ray starts (its servers' start holds the stop signals): the held SIGTERM went, once let
    through, to the handler `ray.init` installs (Ray's own stack dump and SIGABRT, a Ray left running); it stops the
    call as `Stopped` (exit 143), the instance shut down and the caller's SIGTERM handler back."""
    from bitcomm.learn.ray_backend import connect
    from bitcomm.stop_signals import Stopped

    up, shut = [False], []

    def init(*args: Any, **kwargs: Any) -> None:  # as ray.init: its handler in, then the signal, held
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(15))
        up[0] = True
        signal.pthread_kill(threading.main_thread().ident or 0, signal.SIGTERM)  # `timeout`'s, to this thread

    monkeypatch.setattr(ray, "is_initialized", lambda: up[0])
    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setattr(ray, "shutdown", lambda: shut.append(True))
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        with pytest.raises(Stopped) as stop:
            connect(None, 1)
        assert stop.value.exit_code == 128 + signal.SIGTERM and shut == [True]
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["--backend", "nosuch"], "backend"),
        (["--backend", "ray", "--workers", "0"], "workers"),
        (["--backend", "ray", "--workers", "3"], "workers"),  # more actors than the cluster's two CPUs
        (["--backend", "ray", "--staleness", "-1"], "staleness"),
        (["--staleness", "2"], "staleness"),  # asynchrony is Ray's
        (["--address", "127.0.0.1:6379"], "address"),  # an address without --backend ray
        (["--backend", "ray", "--address", "nonsense"], "address"),
        (["--backend", "ray", "--address", "nohost:notaport"], "address"),
        (["--backend", "ray", "--mode", "a3c"], "mode"),
    ],
)
def test_bad_flags_get_one_line(
    cluster: str, argv: list[str], flag: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = main(["train", *TINY, "--episodes", "16", "--out", str(tmp_path / "run"), *argv])
    except SystemExit as exit_:
        code = exit_.code
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert flag in lines[0] and "invalid" in lines[0] and "Traceback" not in lines[0]


def closed_port() -> int:
    """A local TCP port where nothing listens (bound, noted, closed)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.mark.parametrize("scheme", ["", "ray://", "auto"])
def test_an_address_where_nothing_listens_gets_one_line_quickly(
    scheme: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ray itself retried such an address for many minutes ("Failed to connect to GCS ... within 5 seconds"
    every ~40 s): the run stops at once, with one line, before Ray is asked.
    `auto` is checked where Ray finds it (`RAY_ADDRESS` here): before, it made the run folder and then waited."""

    def no_init(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("ray.init was called")

    monkeypatch.setattr(ray, "init", no_init)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)  # as a command's process, not this module's
    address = f"{scheme}127.0.0.1:{closed_port()}"
    if scheme == "auto":
        monkeypatch.setenv("RAY_ADDRESS", address[4:])
        address = "auto"
    out = tmp_path / "run"
    argv = ["train", *TINY, "--episodes", "128", "--backend", "ray", "--workers", "1", "--threads", "1"]
    t0 = time.monotonic()
    code = main([*argv, "--address", address, "--out", str(out)])
    assert time.monotonic() - t0 < 20
    printed = capsys.readouterr()
    lines = printed.err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and not printed.out, (lines, printed.out)  # no "run folder:" line either
    assert lines[0].startswith(f"bitcomm train: error: invalid address='{address}': cannot reach a Ray cluster there (")
    assert "Connection refused" in lines[0]
    assert not out.exists()  # the address is checked before the run folder is made


@pytest.mark.parametrize(
    ("case", "error"),
    [
        ("no ray", "invalid backend='ray': Ray is not installed (pip install 'bitcomm[ray]')"),
        ("3 workers", "invalid workers=3: at most this machine's CPUs (2) on the Ray instance started here: "),
        ("auto", "invalid address='auto': no Ray cluster found (RAY_ADDRESS is not set and no `ray start` runs "),
    ],
)
def test_what_a_ray_run_would_be_refused_is_refused_in_one_line_before_its_folder(
    case: str, error: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ray not importable, more actors than a private instance takes (before, 1000 actors were started on a
    2-core machine, one CPU each), `auto` where Ray finds no cluster: one line, no Ray started (before, the run
    folder was made and "run folder:" printed first)."""

    def no_init(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("ray.init was called")

    monkeypatch.setattr(ray, "init", no_init)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)  # as a command's process, not this module's
    argv = ["train", *TINY, "--episodes", "16", "--backend", "ray", "--workers", "1", "--out", str(tmp_path / "run")]
    if case == "no ray":
        monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails
    elif case == "3 workers":
        monkeypatch.setattr(os, "cpu_count", lambda: 2)
        argv += ["--workers", "3"]
    else:
        import ray._private.services as services

        monkeypatch.delenv("RAY_ADDRESS", raising=False)
        monkeypatch.setattr(services, "find_gcs_addresses", lambda: [])
        monkeypatch.setattr(services, "find_bootstrap_address", lambda temp_dir: None)
        argv += ["--address", "auto"]
    code = main(argv)
    printed = capsys.readouterr()
    lines = printed.err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and not printed.out, (lines, printed.out)
    assert lines[0].startswith(f"bitcomm train: error: {error}"), lines
    assert not (tmp_path / "run").exists()
    if case == "3 workers":  # the default runs on any machine
        from bitcomm.learn.ray_backend import check_ray

        monkeypatch.setattr(os, "cpu_count", lambda: 1)
        check_ray(None, 2)


def test_an_address_of_another_cluster_than_the_one_this_process_is_connected_to_gets_one_line(
    cluster: str, tmp_path: Path
) -> None:
    """A notebook's `ray.init`, then `train(cfg, out, address=...)`: the run trained on the Ray it was connected to,
    whatever cluster the address named. Now an address of another cluster is refused before the run folder is made;
    the connected cluster's own (as Ray gives it or through loopback), `auto` and None train there."""
    from bitcomm.errors import ConfigError
    from bitcomm.learn.ray_backend import check_ray
    from bitcomm.learn.run import train

    port = cluster.rsplit(":", 1)[1]
    for other in ("198.51.100.7:6379", f"127.0.0.1:{closed_port()}", "ray://198.51.100.7:10001"):
        with pytest.raises(ConfigError) as err:
            train(tiny_config(), tmp_path / "run", progress=False, address=other)
        assert str(err.value) == (
            f"invalid address={other!r}: Ray is already connected in this process, to the cluster at {cluster}: "
            "train there without an address (or with auto), or call ray.shutdown() first"
        )
    assert not (tmp_path / "run").exists()
    for same in (cluster, f"127.0.0.1:{port}", f"localhost:{port}", "auto", None):
        check_ray(same, 2)


def test_a_ray_run_checks_what_it_would_be_refused_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`bitcomm train` checked a Ray run (probing its address, up to `PROBE_S`) before it printed the run folder's
    name, and `train` checked it again: two probes a run. The command and `train` check it once each."""
    from bitcomm.learn import ray_backend
    from bitcomm.learn.run import train

    checked: list[tuple[str | None, int]] = []
    monkeypatch.setattr(ray_backend, "check_ray", lambda address, workers: checked.append((address, workers)))
    monkeypatch.setattr(ray_backend, "train_ray", lambda cfg, out, **kwargs: out / "checkpoint")
    address = "198.51.100.7:6379"
    argv = ["train", *TINY, "--episodes", "16", "--backend", "ray", "--workers", "1", "--address", address]
    assert main([*argv, "--out", str(tmp_path / "command")]) == 0
    assert checked == [(address, 1)]
    train(tiny_config(workers=1), tmp_path / "api", progress=False, address=address)
    assert checked == [(address, 1)] * 2


def test_a_private_instance_s_run_prints_no_notice_of_ray_s_token(tmp_path: Path) -> None:
    """Ray 2.5x says at every `ray.init` that starts an instance "Token authentication is enabled for this Ray
    cluster. Set RAY_AUTH_MODE=disabled to opt out...": a line on every run's stderr about an instance only the run
    uses. It is left out; the instance keeps its token."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}  # its own instance, not the module's
    argv = ["train", *TINY, "--episodes", "16", "--backend", "ray", "--workers", "1", "--threads", "1"]
    done = subprocess.run(
        [sys.executable, "-m", "bitcomm.cli", *argv, "--out", str(tmp_path / "run")],
        env={**env, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=STARTUP_S,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "Token authentication" not in done.stderr + done.stdout, done.stderr


def test_the_address_flags_help_names_the_forms_an_address_may_take(capsys: pytest.CaptureFixture[str]) -> None:
    """The help said only "the Ray cluster to train on": the forms were learned from the refusal of a wrong one."""
    assert main(["train", "--help"]) == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert "auto (RAY_ADDRESS, else the last `ray start` here), HOST:PORT or ray://HOST:PORT" in help_text


@pytest.mark.parametrize(
    "address", ["nohost:notaport", "ray://", "host", ":6379", "host:0", "host:65536", "ray://a/b:6379", 6379]
)
def test_a_malformed_address_gets_one_line(address: Any, tmp_path: Path) -> None:
    from bitcomm.errors import ConfigError
    from bitcomm.learn.ray_backend import check_address
    from bitcomm.learn.run import train

    allowed = "must be auto, HOST:PORT or ray://HOST:PORT"
    with pytest.raises(ConfigError) as err:
        check_address(address)
    assert str(err.value) == f"invalid address={address!r}: {allowed}"
    if address == "nohost:notaport":  # through the Python API, without starting Ray
        with pytest.raises(ConfigError, match=f"^invalid address='nohost:notaport': {allowed}$"):
            train(tiny_config(workers=1), tmp_path / "run", progress=False, address=address)


def test_an_address_for_a_config_that_does_not_train_on_ray_gets_one_line(tmp_path: Path) -> None:
    """As `--address` without `--backend ray` does: before, `train` trained locally and left the address unread."""
    from bitcomm.errors import ConfigError
    from bitcomm.learn.run import train

    with pytest.raises(ConfigError, match=r"^invalid address='10.1.2.3:6379': only with backend='ray' \(this config"):
        train(tiny_config(backend="local"), tmp_path / "run", progress=False, address="10.1.2.3:6379")
    assert not (tmp_path / "run").exists()


def test_an_address_check_passes_where_ray_or_another_grpc_server_answers_and_for_auto(
    cluster: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ray's GCS and client servers are gRPC: they answer HTTP/2's preface with a SETTINGS frame."""
    from concurrent.futures import ThreadPoolExecutor

    import grpc

    from bitcomm.errors import ConfigError
    from bitcomm.learn.ray_backend import check_address

    check_address(cluster)  # the GCS, as `ray start --head` prints it
    server = grpc.server(ThreadPoolExecutor(max_workers=1))
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        for address in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}", f"localhost:{port}", None, "auto"):
            check_address(address)
    finally:
        server.stop(None)
    with pytest.raises(ConfigError, match=r"cannot reach a Ray cluster there \(.*nohost\.invalid:6379"):
        check_address("nohost.invalid:6379")  # a name that does not resolve
    with listener(None) as port:  # with TLS only the connection is tried: this probe makes no TLS handshake
        monkeypatch.setenv("RAY_USE_TLS", "1")
        check_address(f"127.0.0.1:{port}")


@contextlib.contextmanager
def listener(reply: bytes | None) -> Iterator[int]:
    """A local TCP port where something that is not Ray listens: silent (None), or reading a request and
    answering `reply` before it hangs up."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        if reply is not None:

            def answer() -> None:
                with contextlib.suppress(OSError):
                    while True:
                        conn, _ = server.accept()
                        with conn:
                            conn.recv(1024)
                            conn.sendall(reply)

            threading.Thread(target=answer, daemon=True).start()
        try:
            yield int(server.getsockname()[1])
        finally:
            with contextlib.suppress(OSError):
                server.shutdown(socket.SHUT_RDWR)  # wakes the thread's accept


def test_an_address_where_a_silent_listener_waits_gets_one_line_within_the_timeout() -> None:
    """Ray hung for many minutes on such an address; the TCP connection alone passed the old probe."""
    from bitcomm.errors import ConfigError
    from bitcomm.learn.ray_backend import check_address

    with listener(None) as port:
        address = f"127.0.0.1:{port}"
        t0 = time.monotonic()
        with pytest.raises(ConfigError) as err:
            check_address(address, timeout=1.0)
        assert time.monotonic() - t0 < 5
    line = str(err.value)
    assert "\n" not in line
    prefix = f"invalid address='{address}': something listens there but does not answer as a Ray cluster (gRPC) does: "
    assert line.startswith(f"{prefix}127.0.0.1:{port}: no answer in time"), line


def test_an_address_where_a_web_server_answers_gets_one_line_quickly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """An HTTP/1 server answers the probe at once: one line, before Ray is asked and the run folder is made."""

    def no_init(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("ray.init was called")

    monkeypatch.setattr(ray, "init", no_init)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)  # as a command's process, not this module's
    out = tmp_path / "run"
    argv = ["train", *TINY, "--episodes", "128", "--backend", "ray", "--workers", "1", "--threads", "1"]
    with listener(b"HTTP/1.1 400 Bad Request\r\n\r\n") as port:
        address = f"ray://127.0.0.1:{port}"
        t0 = time.monotonic()
        code = main([*argv, "--address", address, "--out", str(out)])
        assert time.monotonic() - t0 < 20
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    error = f"bitcomm train: error: invalid address='{address}': something listens there but does not answer as a"
    assert lines[0].startswith(f"{error} Ray cluster (gRPC) does: 127.0.0.1:{port}: it answered 'HTTP/1.1 '"), lines
    assert not out.exists()
