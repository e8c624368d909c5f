"""Asynchronous actor-critic (the paper's training, SPEC section 5): W worker processes, shared weights.

The main process holds the policy and critic in shared memory, with one Adam per network whose
moments also live in shared memory (the classic PyTorch A3C pattern). Each worker:

    # sync      copy the shared weights into its local networks
    # rollout   play `num_envs` whole episodes with its own Collector (batch k: SeedSequence(seed, (k,)))
    # update    the same `Learner.update` as sync mode, on the local copy; every optimizer step of the
    #           learner sends the local (clipped) gradients to the shared parameters and steps the
    #           shared Adam, then reloads the local weights

Episodes are claimed from a shared counter before they are played, so the budget is never exceeded
by more than one batch per worker. The main process only logs and checkpoints (same folder layout
as sync mode). Runs are seeded but, being asynchronous, not reproducible bit for bit.

Ctrl-C or SIGTERM stops the run as sync mode's (`stop_after_batch`): the main process asks the workers to
stop after the batch they are on, logs those batches, saves them and exits through its own cleanup, which
unlinks the lock's and queue's semaphores (killed outright, it left them to the resource tracker's "leaked
semaphore" warning). The workers leave both signals to the main process, as the resource tracker does.

A worker killed outright (`kill -9`, the OOM killer) stops the run the same way: the others end after their
batch, the run saves and ends with one line naming the worker, and `--resume` goes on (before, the others
trained on to the budget unseen and the run then ended in a traceback with nothing saved). A worker killed
holding the shared lock leaves it held: the main process waits `LOCK_WAIT_S` for it, then says so in one line.
"""

from __future__ import annotations

import contextlib
import queue as queue_mod
import time
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp
from torch import nn

from bitcomm.checkpoint import first_nonfinite, resolve
from bitcomm.errors import ConfigError
from bitcomm.learn.allocator import keep_freed_memory
from bitcomm.learn.codebook import CodeBook
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.run_folder import (
    RESUMES,
    Logger,
    Progress,
    checkpoint_weights,
    finite_or_stop,
    learner_state,
    oracle_record,
    prepare,
    restore_learner,
    save_run_checkpoint,
    saved_or_stopped,
    stop_after_batch,
    write_config,
)
from bitcomm.policies.denormals import flush_denormals
from bitcomm.stop_signals import deaf_children, ignore_stop_signals

LOCK_WAIT_S = 30.0
"""How long the main process waits for the shared lock (held for one claim or one optimizer step) before it
takes it for held by a worker that died."""


@contextlib.contextmanager
def _locked(lock: Any, last: str) -> Iterator[None]:
    """`with lock`, but one line rather than a hang when a killed worker left it held (`last`: where the run
    was last saved)."""
    if not lock.acquire(timeout=LOCK_WAIT_S):
        raise ConfigError(
            f"the a3c workers' shared lock was not released in {LOCK_WAIT_S:g} s: a worker killed while it held "
            f"it; the run was last saved as {last}, where {RESUMES}"
        )
    try:
        yield
    finally:
        lock.release()


def _grouped_params(groups: list[dict[str, Any]]) -> list[torch.Tensor]:
    """The parameters of optimizer groups, group by group: the order shared Adam states are listed in."""
    return [p for g in groups for p in g["params"]]


def share_adam_state(opt: torch.optim.Optimizer) -> list[dict[str, torch.Tensor]]:
    """Create (if empty) Adam's per-parameter state and move it to shared memory; in `_grouped_params` order."""
    out = []
    for p in _grouped_params(opt.param_groups):
        st = opt.state[p]
        if not st:
            st["step"] = torch.zeros((), dtype=torch.float32)
            st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        for v in st.values():
            if isinstance(v, torch.Tensor):
                v.share_memory_()
        out.append(st)
    return out


class SharedStep:
    """Stands in for the learner's optimizer in a worker: `step()` applies the local gradients to the
    shared parameters with the shared Adam, then copies the shared weights back into the local net."""

    def __init__(
        self,
        local: nn.Module,
        shared: nn.Module,
        states: list[dict[str, torch.Tensor]],
        template: torch.optim.Optimizer,
        lock: Any,
    ) -> None:
        self.local, self.shared, self.lock = list(local.parameters()), list(shared.parameters()), lock
        index = {id(p): k for k, p in enumerate(self.local)}
        groups = [  # the local optimizer's groups (and their learning rates), over the shared parameters
            {**g, "params": [self.shared[index[id(p)]] for p in g["params"]]} for g in template.param_groups
        ]
        self.opt = torch.optim.Adam(groups)
        for p, st in zip(_grouped_params(groups), states, strict=True):
            self.opt.state[p] = st

    @property
    def param_groups(self) -> list[dict[str, Any]]:
        """The shared Adam's groups, so the learner can set their learning rates (`anneal_lr`)."""
        return self.opt.param_groups

    def step(self) -> None:
        for lp, sp in zip(self.local, self.shared, strict=True):
            sp.grad = lp.grad
        with self.lock:
            self.opt.step()
        pull(self.local, self.shared)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.local:
            p.grad = None


@torch.no_grad()
def pull(local: Sequence[torch.Tensor], shared: Sequence[torch.Tensor]) -> None:
    for lp, sp in zip(local, shared, strict=True):
        lp.copy_(sp)


def _worker(
    w: int,
    cfg: TrainConfig,
    shared: tuple[nn.Module, nn.Module, CodeBook | None],
    states: tuple[list[dict[str, torch.Tensor]], list[dict[str, torch.Tensor]]],
    lock: Any,
    claimed: Any,
    next_batch: Any,
    results: Any,
    formed: Any,
    stop: Any,
) -> None:
    ignore_stop_signals()
    try:
        from bitcomm.learn.learner import Learner
        from bitcomm.learn.rollout import Collector

        torch.set_num_threads(1)
        keep_freed_memory()
        worker_seed = np.random.SeedSequence(cfg.seed, spawn_key=(1 << 30, w)).generate_state(2)
        torch.manual_seed(int(worker_seed[0]))
        generator = torch.Generator().manual_seed(int(worker_seed[1]))
        learner = Learner(cfg)
        learner.codebook = shared[2]
        learner.opt_policy = SharedStep(learner.policy, shared[0], states[0], learner.opt_policy, lock)  # type: ignore[assignment]
        learner.opt_critic = SharedStep(learner.critic, shared[1], states[1], learner.opt_critic, lock)  # type: ignore[assignment]
        local = list(learner.policy.parameters()) + list(learner.critic.parameters())
        remote = list(shared[0].parameters()) + list(shared[1].parameters())
        collector = Collector(cfg.training_task, cfg.num_envs)
        results.put(("ready", w))  # started: the run's seconds of training count from the first worker's
        parent = mp.parent_process()
        while True:
            if parent is not None and not parent.is_alive():  # the main process was killed: stop, do not linger
                results.cancel_join_thread()
                return
            with lock:
                if claimed.value >= cfg.episodes or stop.value:
                    break
                claimed_before = claimed.value
                claimed.value += cfg.num_envs
                k = next_batch.value
                next_batch.value += 1
            # sync, rollout, update
            pull(local, remote)
            with flush_denormals():
                seed = np.random.SeedSequence(cfg.seed, spawn_key=(k,))
                start = formed.value if formed.value >= 0 else None  # where the main process saw the protocol form
                greedy = cfg.greedy_sender_episodes(claimed_before, start)
                held = cfg.held_message_episodes(claimed_before, start)
                ro = collector.collect(learner.policy, seed, generator, greedy, held)
                stats = learner.update(ro, generator, progress=cfg.schedule_progress(claimed_before))
            sent_greedy = ro.sent_greedy.numpy().copy()
            results.put(("batch", w, ro.length.copy(), ro.team_return.copy(), ro.success.copy(), sent_greedy, stats))
        results.put(("done", w))
    except BaseException:  # report, so the main process stops with the worker's traceback
        results.put(("error", w, traceback.format_exc()))


def train_a3c(cfg: TrainConfig, out: Path, resume: bool = False, progress: bool = True) -> Path:
    from tqdm import tqdm

    from bitcomm.learn.learner import Learner

    cfg, saved = prepare(cfg, out, resume)
    torch.manual_seed(cfg.seed)
    learner = Learner(cfg)
    prog = Progress()
    start_batch = 0
    if saved is not None:
        restore_learner(learner, saved)
        prog.restore(saved)
        start_batch = int(saved.get("next_batch", prog.batches))
    write_config(cfg, out, saved, oracle_record)
    logger = Logger(out, prog.batches if saved is not None else None)
    n = cfg.task.env.n_agents

    learner.policy.share_memory()
    learner.critic.share_memory()
    if learner.codebook is not None:  # one book for every worker, or they would teach different codes
        learner.codebook.share_memory()
    states = (share_adam_state(learner.opt_policy), share_adam_state(learner.opt_critic))
    ctx = mp.get_context("spawn")
    lock = ctx.Lock()
    claimed = ctx.Value("q", prog.episodes, lock=False)
    next_batch = ctx.Value("q", start_batch, lock=False)
    formed = ctx.Value("d", _or_unset(learner.senders_wait.start), lock=False)  # SendersWait.start, -1: not yet
    stop = ctx.Value("b", 0, lock=False)  # 1: the main process was asked to stop
    results = ctx.Queue()
    shared = (learner.policy, learner.critic, learner.codebook)
    procs = [
        ctx.Process(
            target=_worker,
            args=(w, cfg, shared, states, lock, claimed, next_batch, results, formed, stop),
            daemon=True,
        )
        for w in range(cfg.workers)
    ]

    saved_as = [str(resolve(out)) if saved is not None else "nowhere (no checkpoint yet)"]

    def save() -> Path:
        with _locked(lock, saved_as[0]):  # weights and Adam moments from between two steps
            weights = {k: {n_: t.clone() for n_, t in sd.items()} for k, sd in checkpoint_weights(learner).items()}
            state = {
                **prog.state(),
                **learner_state(learner),
                "next_batch": next_batch.value,
            }
            state = {k: _clone(v) for k, v in state.items()}
        path = save_run_checkpoint(out, cfg, weights, prog, state)
        saved_as[0] = str(path)
        return path

    bar = tqdm(total=cfg.episodes, initial=prog.episodes, disable=not progress, unit="ep", dynamic_ncols=True)
    t_start, wall0 = time.perf_counter(), prog.wall_s
    last_save = time.monotonic()
    done: set[int] = set()
    died: dict[int, int] = {}  # worker -> exit code, of the workers killed (not one that reported an error)
    heard: set[int] = set()  # the workers that sent a batch
    started = False  # a worker has started (its `Learner` built): the run's seconds of training count from then
    with stop_after_batch() as stop_asked:  # till the workers are gone: a signal meanwhile is a request
        try:
            with deaf_children():  # till `ignore_stop_signals`: killed mid-batch, a worker could hold the lock
                for p in procs:
                    p.start()
            while len(done) < len(procs):
                for w, p in enumerate(procs):  # checked at every message: the others keep the queue busy
                    if w not in done and p.exitcode not in (None, 0):
                        died[w] = p.exitcode
                        done.add(w)
                if stop_asked() is not None or died:  # the workers end after the batch they are on
                    stop.value = 1
                try:
                    msg = results.get(timeout=1.0)
                except queue_mod.Empty:
                    if died:  # the others may wait on a lock the dead one held
                        with _locked(lock, saved_as[0]):
                            pass
                    continue
                if msg[0] == "error":
                    with _locked(lock, saved_as[0]):
                        if first_nonfinite(**checkpoint_weights(learner)):  # a worker failed on NaN weights: say so
                            finite_or_stop(out, learner, prog.episodes)
                    raise RuntimeError(f"a3c worker {msg[1]} failed:\n{msg[2]}")
                if msg[0] == "done":
                    done.add(msg[1])
                    continue
                if msg[0] == "ready":
                    if not started:  # a process spawned and its imports are not training: a resume would add them
                        t_start, started = time.perf_counter(), True
                    continue
                _, w, length, team_return, success, sent_greedy, stats = msg
                heard.add(w)
                prog.wall_s = wall0 + time.perf_counter() - t_start
                learner.senders_wait.watch(prog.rolling_length, cfg.schedule_progress(prog.episodes))  # as sync's
                formed.value = _or_unset(learner.senders_wait.start)
                row = prog.add_batch(length, team_return, int(length.sum()) * n, sent_greedy=sent_greedy)
                row.update({"charts/success": float(success.mean()), **stats})
                # the main process watches, not the worker whose stats these are
                row.update(learner.senders_wait.figures())
                # between two steps, as `save` reads: unlocked, this check once found a NaN that no worker's step
                # had before or after it (docs/tuning.md session 48)
                with _locked(lock, saved_as[0]):
                    finite_or_stop(out, learner, prog.episodes)
                logger.log(row)
                # workers overshoot the budget: the bar stops at it
                bar.update(min(len(length), max(0, bar.total - bar.n)))
                rolling, recent = row["charts/episode_length_rolling"], np.mean(prog.recent_return)
                bar.set_postfix(len=f"{rolling:.1f}", ret=f"{recent:.2f}")
                if time.monotonic() - last_save >= cfg.checkpoint_seconds and claimed.value < cfg.episodes:
                    save()
                    last_save = time.monotonic()
            for p in procs:
                p.join()
            if died:
                path = save()
                w, code = next(iter(died.items()))
                raise ConfigError(
                    f"a3c worker {w} (pid {procs[w].pid}) died (exit code {code}); the others stopped after their "
                    f"batch, saved after {prog.episodes} episodes as {path}; {RESUMES}"
                    + (NO_BATCH_HINT if code == 1 and w not in heard else "")  # an error, not a kill
                )
            return saved_or_stopped(stop_asked, prog.episodes, save, bar)
        finally:
            for p in procs:
                if p.pid is None:  # never started (start() itself failed)
                    continue
                if p.is_alive():  # after an error or a second signal: it ignores SIGTERM (`ignore_stop_signals`)
                    p.kill()
                p.join(timeout=5)
            bar.close()
            logger.close()


NO_BATCH_HINT = (
    " (it failed before its first batch: from a script, a3c's workers, started afresh by multiprocessing's spawn, "
    'need the training call under `if __name__ == "__main__":`; the worker\'s own message is above)'
)
"""What most often kills a worker before it plays: a script without the guard spawn needs runs its training again in
each worker, and Python stops it there."""


def _or_unset(start: float | None) -> float:
    """A watch's start as a shared double: -1 for not yet."""
    return -1.0 if start is None else start


def _clone(v: Any) -> Any:
    """A deep copy of tensors inside dicts and lists (the shared ones keep changing)."""
    if isinstance(v, torch.Tensor):
        return v.clone()
    if isinstance(v, dict):
        return {k: _clone(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_clone(x) for x in v]
    return v
