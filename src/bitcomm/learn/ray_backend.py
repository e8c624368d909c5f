"""Training on a Ray cluster (`backend="ray"`, docs/distributed.md): rollout actors collect, one learner here updates.

    # actors    `workers` rollout actors, each with its own Collector (`num_envs` episodes a batch) and a CPU copy
    #           of the policy
    # publish   after each update the policy's weights go to the object store once (`ray.put`); every actor's
    #           next batch is asked for with that reference, so a node fetches the weights once, not once per actor
    # collect   batch k plays the episodes of `SeedSequence(seed, (k,))` (as sync mode does) and samples with a
    #           generator seeded by (seed, k); it comes back as numpy arrays with the weights version it was played with
    # learn     staleness 0: wait for the batches of all actors, join them (in batch order) and make one
    #           `Learner.update`; staleness S > 0: update on each batch as it arrives (`ray.wait`), dropping (and
    #           counting) a batch played with weights more than S updates old; metrics.csv records each
    #           update's staleness
    # faults    an actor that dies is replaced and the batch it was playing is asked of the new one; checkpoints
    #           are the local trainers' (atomic, same state), so a run resumes on either backend
    # stop      Ctrl-C or SIGTERM (`stop_after_batch`; SIGTERM taken back from the handler `ray.init` installs,
    #           which ended the run unsaved) launches no more batches: the ones in flight are consumed, the run saves
    #           and exits as sync mode's does (130, 143), and `--resume` goes on

Reproducible: with staleness 0 a run is bit for bit the same for a given seed, `workers` and `num_envs` (which
batches an update joins and the weights each was played with are fixed), through actor deaths and resumes.
Asynchronous runs are seeded (a batch's episodes and samples are fixed by its index) but which weights a batch
meets depends on timing, so they are not. The row's `batch` counts batches consumed, so a local resume plays
the next batch index; batches dropped for staleness or lost in flight were played but not counted.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import signal
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.errors import ConfigError, bad_value
from bitcomm.learn.allocator import keep_freed_memory
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.ray_address import ADDRESS_FORMS, host_port
from bitcomm.learn.rollout import Collector, Rollout
from bitcomm.learn.run_folder import (
    Logger,
    Progress,
    finite_or_stop,
    oracle_record,
    prepare,
    restore_learner,
    save_learner,
    saved_or_stopped,
    stop_after_batch,
    write_config,
)
from bitcomm.policies.denormals import flush_denormals
from bitcomm.policies.networks import PolicyNet
from bitcomm.stop_signals import deaf_children, sigterm_interrupts

ACTOR_PREFIX = "bitcomm-rollout"
"""Rollout actors are named `<prefix>-<run token>-<worker>.<generation>` (`ray.util.list_named_actors` lists them)."""
MAX_FAILURES = 3
"""An actor that dies this many times in a row before delivering a batch stops the run with the cause (a node
that cannot start one: bitcomm or a dependency missing there) instead of being replaced forever."""
SAMPLE_KEY = 1 << 31
"""Batch k samples moves and bits with `SeedSequence(seed, (SAMPLE_KEY, k))`, apart from its episodes' seeds."""
EPISODE_FIELDS = ("length", "team_return", "success", "goal", "sent_greedy")
"""Rollout fields indexed by episode only; the others are time-major `(T, B, ...)`."""


def sample_seed(seed: int, batch: int) -> int:
    """The seed of batch `batch`'s sampling generator."""
    return int(np.random.SeedSequence(seed, spawn_key=(SAMPLE_KEY, batch)).generate_state(1)[0])


class RolloutWorker:
    """Plays batches with its own envs and a CPU copy of the policy (run as a Ray actor)."""

    def __init__(self, config: dict[str, Any]) -> None:
        torch.set_num_threads(1)
        keep_freed_memory()
        self.cfg = TrainConfig.from_dict(config)
        self.policy = PolicyNet(self.cfg.task, self.cfg.model)
        self.collector = Collector(self.cfg.training_task, self.cfg.num_envs)
        self.version = -1

    def ready(self) -> bool:
        """Answered once the actor is built (its process started, its imports done, its envs made)."""
        return True

    def collect(
        self, weights: dict[str, np.ndarray], version: int, batch: int, formed: float | None = 0.0
    ) -> dict[str, Any]:
        """Batch `batch` played with weights `version`, the protocol formed at progress `formed` (the driver's
        `SendersWait.start`): its Rollout as numpy arrays plus the bookkeeping."""
        if version != self.version:
            self.policy.load_state_dict({k: torch.tensor(v) for k, v in weights.items()})
            self.version = version
        t0 = time.perf_counter()
        generator = torch.Generator().manual_seed(sample_seed(self.cfg.seed, batch))
        seed = np.random.SeedSequence(self.cfg.seed, spawn_key=(batch,))
        with flush_denormals():
            before = batch * self.cfg.num_envs  # the episodes of the batches before it: full ones
            greedy = self.cfg.greedy_sender_episodes(before, formed)
            held = self.cfg.held_message_episodes(before, formed)
            ro = self.collector.collect(self.policy, seed, generator, greedy, held)
        arrays = {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in ro._asdict().items()}
        return {"batch": batch, "version": version, "collect_s": time.perf_counter() - t0, "rollout": arrays}


def join(rollouts: list[dict[str, np.ndarray]]) -> Rollout:
    """Rollouts side by side as one (episodes joined, time padded with invalid steps to the longest); fresh
    writable arrays, whatever the object store handed back."""
    T = max(r["valid"].shape[0] for r in rollouts)
    fields: dict[str, Any] = {}
    for name in Rollout._fields:
        parts = [r[name] for r in rollouts]
        if name in EPISODE_FIELDS:
            fields[name] = np.concatenate(parts)
            continue
        out = np.zeros((T, sum(p.shape[1] for p in parts), *parts[0].shape[2:]), dtype=parts[0].dtype)
        col = 0
        for p in parts:
            out[: p.shape[0], col : col + p.shape[1]] = p
            col += p.shape[1]
        fields[name] = out
    numpy = ("length", "team_return", "success")
    tensors: dict[str, Any] = {k: v if k in numpy else torch.from_numpy(v) for k, v in fields.items()}
    return Rollout(**tensors)


PROBE_S = 5.0
"""How long `check_address` gives an explicit `HOST:PORT` to accept a TCP connection and answer as gRPC before
refusing it: Ray itself retries an address where nothing listens for many minutes (20 tries of about 40 s, each
logging "Failed to connect to GCS"), and hangs as long where something that is not Ray listens."""
GRPC_HELLO = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
"""HTTP/2's client preface and an empty SETTINGS frame: a gRPC server (Ray's GCS and client servers) answers
with a SETTINGS frame at once; a silent listener or an HTTP/1 server does not."""


def import_ray() -> Any:
    """The `ray` module; one line where it cannot be imported."""
    try:
        import ray
    except ImportError:
        raise bad_value("backend", "ray", "Ray is not installed (pip install 'bitcomm[ray]')") from None
    return ray


def private_cpus() -> int:
    """The most rollout actors a private Ray instance (no `address`) takes: this machine's CPUs, and at least
    `TrainConfig.workers`' default, so that the default runs anywhere."""
    return max(os.cpu_count() or 1, TrainConfig.workers)


def check_ray(address: str | None, workers: int) -> None:
    """What `connect` would refuse, checked before the run folder is made, in one line: Ray not installed, an
    address where no cluster answers (`check_address`) or that names another cluster than the one this process is
    connected to (`check_connected`), or more actors than a private instance takes (`private_cpus`; a cluster's CPUs
    are known once connected). Starts nothing."""
    ray = import_ray()
    if ray.is_initialized():
        check_connected(ray, address)
        return
    if address is None and workers > (cpus := private_cpus()):
        raise bad_value(
            "workers",
            workers,
            f"at most this machine's CPUs ({cpus}) on the Ray instance started here: each rollout actor takes one "
            "(more: a cluster's, with --address)",
        )
    check_address(address)


def check_connected(ray: Any, address: str | None) -> None:
    """One line where Ray is connected in this process (a notebook's `ray.init`) and `address` names another
    cluster: `connect` trains on the connected one, and the address would be silently ignored. None and `auto` take
    the connected cluster; `HOST:PORT` must be its GCS (`_same_cluster`)."""
    if address is None or (parts := _parsed(address)) is None:
        return
    connected = ray.get_runtime_context().gcs_address
    if not _same_cluster(address, parts, connected):
        raise bad_value(
            "address",
            address,
            f"Ray is already connected in this process, to the cluster at {connected}: train there without an "
            "address (or with auto), or call ray.shutdown() first",
        )


def _same_cluster(address: str, parts: tuple[str, int], connected: str) -> bool:
    """Whether `address` (`parts`: its host and port) names the cluster whose GCS is at `connected`: the same port on
    the same machine; a `ray://` one is a Ray Client server's, on the head beside the GCS, so the machine alone."""
    gcs = host_port(connected)
    if gcs is None:  # an address Ray gives in a form this does not read: nothing to compare
        return True
    host, port = parts
    same_port = address.strip().startswith("ray://") or port == gcs[1]
    return same_port and not _machine(host).isdisjoint(_machine(gcs[0]))


def _machine(host: str) -> set[str]:
    """The IP addresses `host` stands for, this node's for a loopback one (`_candidates`); the name itself where it
    does not resolve."""
    ips: set[str] = set()
    for candidate in _candidates(host):
        try:
            ips |= {str(info[4][0]) for info in socket.getaddrinfo(candidate, None)}
        except OSError:
            ips.add(candidate)
    return ips


def _parsed(address: object) -> tuple[str, int] | None:
    """`address`'s host and port, None for `auto`; one line for anything that is not an address."""
    if not isinstance(address, str):
        raise bad_value("address", address, ADDRESS_FORMS)
    if address.strip() == "auto":
        return None
    parts = host_port(address)
    if parts is None:
        raise bad_value("address", address, ADDRESS_FORMS)
    return parts


def check_address(address: str | None, timeout: float = PROBE_S) -> None:
    """One line, within about `timeout` seconds, unless `address` is None, `auto` where Ray finds a cluster
    (`RAY_ADDRESS`, else the last `ray start` on this machine) that answers, or a `HOST:PORT` (or
    `ray://HOST:PORT`) where a gRPC server answers (a TCP connection is enough with `RAY_USE_TLS`, whose
    handshake this does not make): Ray would wait for anything else for many minutes. Starts nothing, so a
    caller may check before it makes the run folder."""
    if address is None:
        return
    parts = _parsed(address)
    if parts is None and (found := _auto(address)) is not None:
        parts = host_port(found)
    if parts is None:
        return
    host, port = parts
    tls = os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true")
    deadline = time.monotonic() + timeout
    reasons, listens = [], False
    for candidate in _candidates(host):
        try:
            with socket.create_connection((candidate, port), timeout=_left(deadline)) as sock:
                answer = "" if tls else _not_grpc(sock, deadline)
        except OSError as err:
            reasons.append(f"{candidate}:{port}: {err.strerror or err or type(err).__name__}")
            continue
        if not answer:
            return
        reasons.append(f"{candidate}:{port}: {answer}")
        listens = True
    why = "; ".join(reasons)
    if listens:
        raise bad_value(
            "address", address, f"something listens there but does not answer as a Ray cluster (gRPC) does: {why}"
        )
    raise bad_value("address", address, f"cannot reach a Ray cluster there (nothing accepts a connection: {why})")


def _auto(address: str) -> str | None:
    """Where Ray's `auto` leads (a `HOST:PORT`, probed as a typed one), one line where it finds no cluster; None
    where this Ray cannot say (its lookup is not public API)."""
    try:
        from ray._private.services import get_ray_address_from_environment
    except ImportError:
        return None
    try:
        found = get_ray_address_from_environment(address, None)
    except ConnectionError:
        raise bad_value(
            "address", address, "no Ray cluster found (RAY_ADDRESS is not set and no `ray start` runs on this machine)"
        ) from None
    except Exception:  # noqa: BLE001 - Ray's own, which ray.init meets again and reports
        return None
    return found if isinstance(found, str) and host_port(found) is not None else None


def _left(deadline: float) -> float:
    """Seconds to `deadline`, at least a little, so a later candidate still gets a try."""
    return max(0.1, deadline - time.monotonic())


def _not_grpc(sock: socket.socket, deadline: float) -> str:
    """'' if the server on `sock` answers `GRPC_HELLO` with a SETTINGS frame before `deadline`, else what it did."""
    reply, silence = b"", "it hung up"
    try:
        sock.sendall(GRPC_HELLO)
        while len(reply) < 9:
            sock.settimeout(_left(deadline))
            chunk = sock.recv(9 - len(reply))
            if not chunk:
                break
            reply += chunk
    except TimeoutError:
        silence = "no answer in time"
    except OSError as err:
        silence = err.strerror or str(err) or type(err).__name__
    if len(reply) == 9 and reply[3] == 0x04:
        return ""
    return f"it answered {reply.decode('latin-1')!r}" if reply else silence


def _candidates(host: str) -> Iterator[str]:
    """Where to look for `host`'s head: the host; for a loopback one also this node's IP, which Ray connects to
    instead (a head listening there only is fine)."""
    yield host
    if host in ("localhost", "127.0.0.1", "::1"):
        try:
            from ray.util import get_node_ip_address

            node = get_node_ip_address()
        except Exception:  # no Ray, or no route: the loopback answer stands
            return
        if node != host:
            yield node


TOKEN_NOTICE = "ray._private.authentication.authentication_token_setup"
"""The logger where Ray (2.5x) says, at every `ray.init` that starts an instance, that it turned token
authentication on ("Token authentication is enabled for this Ray cluster. Set RAY_AUTH_MODE=disabled to opt
out..."): a notice on every run's stderr about an instance only the run uses, not a fault."""


@contextlib.contextmanager
def no_token_notice() -> Iterator[None]:
    """Ray's notice that a private instance has token authentication (`TOKEN_NOTICE`) left out while it starts;
    that logger's errors still show, and the instance keeps its token."""
    logger = logging.getLogger(TOKEN_NOTICE)
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def connect(address: str | None, workers: int) -> tuple[bool, Any]:
    """Join the cluster at `address`, shipping this bitcomm package to its workers (Ray's `py_modules`: the
    nodes need its dependencies, not bitcomm); None: a Ray already started in this process, else a new local
    instance with a CPU per actor, whose servers (in the driver's process group) are deaf to the stop signals the
    driver takes (`deaf_children`), so that the driver can save. Returns whether this call started Ray (and shuts
    it down again if anything stops the call after) and the SIGTERM handler `ray.init` installed, which ends a run
    unsaved (`sys.exit(15)`): the caller's is back in its place, before a stop signal held while the private
    instance started is let through (one ended the driver with Ray's stack dump, SIGABRT); a SIGTERM meanwhile
    raises `Stopped` (`sigterm_interrupts`), where nothing else takes it. One line if no
    cluster answers or it is too small (`bitcomm.learn.run.train` has checked the address with `check_address`
    before making the run folder)."""
    with sigterm_interrupts():  # a SIGTERM while Ray starts stops the call, which shuts that Ray down
        return _connect(address, workers)


def _connect(address: str | None, workers: int) -> tuple[bool, Any]:
    import ray

    import bitcomm

    before = rays = signal.getsignal(signal.SIGTERM)
    started = False
    try:
        if not ray.is_initialized():
            try:
                with deaf_children() if address is None else contextlib.nullcontext():
                    try:
                        if address is None:
                            cpus = max(workers, os.cpu_count() or 1)
                            with no_token_notice():
                                ray.init(
                                    "local",
                                    num_cpus=cpus,
                                    include_dashboard=False,
                                    log_to_driver=False,
                                    configure_logging=False,
                                )
                        else:
                            code = {"py_modules": [str(Path(bitcomm.__file__).parent)]}
                            ray.init(address, runtime_env=code, log_to_driver=False, configure_logging=False)
                    finally:
                        started = ray.is_initialized()
                        rays = signal.getsignal(signal.SIGTERM)
                        _set_sigterm(before)
            except (ConnectionError, RuntimeError, ValueError) as err:
                reason = f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"
                raise bad_value("address", address, f"no Ray cluster answers there ({reason})") from None
        cpus = ray.cluster_resources().get("CPU", 0)
        if cpus < workers:
            raise bad_value(
                "workers", workers, f"at most the Ray cluster's CPUs ({cpus:g}): each rollout actor takes one"
            )
    except BaseException:
        if started:
            _set_sigterm(rays)
            ray.shutdown()
        raise
    return started, rays


def _cause(err: Exception) -> str:
    """The last line of a Ray error (the exception that killed the actor), without colour codes."""
    lines = [line.strip() for line in re.sub(r"\x1b\[[0-9;]*m", "", str(err)).splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


class Actors:
    """The rollout actors and the batches they are playing; replaces an actor that dies."""

    def __init__(self, cfg: TrainConfig) -> None:
        import ray

        self.ray = ray
        self.cls = ray.remote(num_cpus=1)(RolloutWorker)
        self.config = cfg.to_dict()
        self.token = uuid.uuid4().hex[:8]
        self.generation = [0] * cfg.workers
        self.actors = [self._start(w) for w in range(cfg.workers)]
        self.inflight: dict[Any, tuple[int, int, float | None]] = {}  # object ref -> (worker, batch, formed)
        self.restarts = 0
        self.failures = [0] * cfg.workers  # deaths in a row without a batch delivered

    def _start(self, w: int) -> Any:
        name = f"{ACTOR_PREFIX}-{self.token}-{w}.{self.generation[w]}"
        return self.cls.options(name=name).remote(self.config)  # type: ignore[attr-defined]

    def started(self) -> None:
        """Wait for the actors to be built: processes started and their imports are not training, and counted in
        `wall_s` they would be added again at every resume (an actor that failed to start is met, and replaced, when
        its first batch is asked for)."""
        self.ray.wait([a.ready.remote() for a in self.actors], num_returns=len(self.actors))

    def launch(self, w: int, batch: int, weights: Any, version: int, formed: float | None = 0.0) -> None:
        self.inflight[self.actors[w].collect.remote(weights, version, batch, formed)] = (w, batch, formed)

    def receive(self, weights: Any, version: int) -> tuple[int, dict[str, Any]] | None:
        """The next batch to arrive, with its worker; None when that worker died (it is replaced and asked for
        the same batch with the latest weights)."""
        ready, _ = self.ray.wait(list(self.inflight), num_returns=1)
        w, batch, formed = self.inflight.pop(ready[0])
        try:
            result = self.ray.get(ready[0])
        except self.ray.exceptions.RayActorError as err:
            self.failures[w] += 1
            if self.failures[w] >= MAX_FAILURES:
                raise ConfigError(
                    f"invalid backend='ray': rollout actor {w} died {MAX_FAILURES} times in a row before delivering "
                    f"a batch (last: {_cause(err)})"
                ) from None
            self.restarts += 1
            self.generation[w] += 1
            self.actors[w] = self._start(w)
            self.launch(w, batch, weights, version, formed)
            return None
        self.failures[w] = 0
        return w, result

    def stop(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor)


def train_ray(
    cfg: TrainConfig, out: Path, resume: bool = False, progress: bool = True, address: str | None = None
) -> Path:
    """Train on Ray until `cfg.episodes` episodes are consumed; the caller holds the run folder's lock
    (`bitcomm.learn.run.train`). Returns the latest checkpoint."""
    ray = import_ray()
    if cfg.backend != "ray":
        raise bad_value("backend", cfg.backend, "train_ray needs backend='ray'")
    started, rays = connect(address, cfg.workers)  # `_train` stops the run saved, where `ray.init`'s handler did not
    try:
        return _train(cfg, out, resume, progress)
    finally:
        _set_sigterm(rays)
        if started:
            ray.shutdown()


def _set_sigterm(handler: Any) -> None:
    """Make `handler` SIGTERM's where Python can (in the main thread, a handler Python knows of)."""
    if handler is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)


def _policy_weights(policy: torch.nn.Module) -> dict[str, np.ndarray]:
    return {k: v.detach().numpy() for k, v in policy.state_dict().items()}


def _train(cfg: TrainConfig, out: Path, resume: bool, progress: bool) -> Path:
    import ray
    from tqdm import tqdm

    from bitcomm.learn.learner import Learner

    cfg, saved = prepare(cfg, out, resume)
    torch.manual_seed(cfg.seed)
    learner = Learner(cfg)
    generator = torch.Generator().manual_seed(cfg.seed)
    prog = Progress()
    next_batch = 0
    if saved is not None:
        restore_learner(learner, saved)
        if "generator" in saved:  # an a3c checkpoint has none
            generator.set_state(saved["generator"])
        torch.set_rng_state(saved["torch_rng"])
        prog.restore(saved)
        next_batch = int(saved.get("next_batch", prog.batches))
    write_config(cfg, out, saved, oracle_record)
    logger = Logger(out, prog.batches if saved is not None else None)
    n, S, N = cfg.task.env.n_agents, cfg.staleness, cfg.workers
    version, dropped = 0, 0
    weights = ray.put(_policy_weights(learner.policy))

    def save() -> Path:
        return save_learner(out, cfg, learner, generator, prog, extra={"next_batch": next_batch})

    actors = Actors(cfg)
    planned = -(-cfg.episodes // cfg.num_envs) * cfg.num_envs
    bar = tqdm(total=planned, initial=prog.episodes, disable=not progress, unit="ep", dynamic_ncols=True)
    t_start, wall0, last_save = time.perf_counter(), prog.wall_s, time.monotonic()

    def consume(batches: list[dict[str, Any]], staleness: int) -> None:
        nonlocal version, weights, last_save
        ro = join([b["rollout"] for b in batches])
        t0 = time.perf_counter()
        stats = learner.update(
            ro, generator, progress=cfg.schedule_progress(prog.episodes), rolling_length=prog.rolling_length
        )
        finite_or_stop(out, learner, prog.episodes + len(ro.length))
        version += 1
        weights = ray.put(_policy_weights(learner.policy))  # once per update, whatever the number of actors
        update_s = time.perf_counter() - t0
        prog.wall_s = wall0 + time.perf_counter() - t_start
        sent_greedy = ro.sent_greedy.numpy()
        row = prog.add_batch(ro.length, ro.team_return, int(ro.length.sum()) * n, len(batches), sent_greedy)
        row.update(
            {
                "charts/success": float(ro.success.mean()),
                **stats,
                "ray/staleness": staleness,
                "ray/dropped": dropped,
                "ray/restarts": actors.restarts,
                "ray/update_s": update_s,
                "ray/collect_s": float(np.mean([b["collect_s"] for b in batches])),
            }
        )
        logger.log(row)
        bar.update(len(ro.length))
        bar.set_postfix(len=f"{row['charts/episode_length_rolling']:.1f}", ret=f"{np.mean(prog.recent_return):.2f}")
        if time.monotonic() - last_save >= cfg.checkpoint_seconds and prog.episodes < cfg.episodes:
            save()
            last_save = time.monotonic()

    def launch(w: int) -> None:
        nonlocal next_batch
        actors.launch(w, next_batch, weights, version, learner.senders_wait.start)
        next_batch += 1

    def wanted() -> bool:
        return prog.episodes + len(actors.inflight) * cfg.num_envs < cfg.episodes and stop_asked() is None

    with stop_after_batch() as stop_asked:  # a stop signal meanwhile is a request: in-flight batches are used
        try:
            actors.started()
            t_start = time.perf_counter()  # the run's seconds of training count from here (`Actors.started`)
            if S == 0:  # synchronous: every actor plays one batch with the same weights, one update on them all
                while prog.episodes < cfg.episodes and stop_asked() is None:
                    for w in range(min(N, math.ceil((cfg.episodes - prog.episodes) / cfg.num_envs))):
                        launch(w)
                    got = []
                    while actors.inflight:
                        if (arrived := actors.receive(weights, version)) is not None:
                            got.append(arrived[1])
                    consume(sorted(got, key=lambda b: b["batch"]), 0)
            else:  # asynchronous: update on each batch as it arrives, within the staleness bound
                for w in range(N):
                    if wanted():
                        launch(w)
                while actors.inflight:
                    if (arrived := actors.receive(weights, version)) is None:
                        continue
                    w, batch = arrived
                    if version - batch["version"] > S:
                        dropped += 1
                    else:
                        consume([batch], version - batch["version"])
                    if wanted():
                        launch(w)
            return saved_or_stopped(stop_asked, prog.episodes, save, bar)
        finally:
            actors.stop()
            bar.close()
            logger.close()
