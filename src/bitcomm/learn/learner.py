"""One learning update from a batch of whole episodes, shared by the sync and A3C trainers.

# features   the networks' parameter-free reading of the observations, once per batch (marginals encoders)
# baselines  critics evaluated once per batch (V1 for standard, V2 with masks for improved)
# advantages the estimator chosen by name (bitcomm.learn.estimators), optionally normalised
# update     per minibatch: the recipe's objective terms (bitcomm.learn.objectives) summed per clip
#            group, each group clipped on its own, one policy step; the critic term, one critic step

The learner speaks the rollout's tensors (`bitcomm.learn.rollout.Rollout`); the networks it owns
(`bitcomm.policies.networks`) are where the task's observation layout is read.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import torch

from bitcomm.config import critic_passes
from bitcomm.learn.beside import start
from bitcomm.learn.codebook import CodeBook
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.distinct import distinct_rows
from bitcomm.learn.estimators import Advantages, EstimatorBatch, get_estimator
from bitcomm.learn.level_watch import SendersWait
from bitcomm.learn.move_decay import MoveDecay
from bitcomm.learn.objectives import Routes, StepBatch, Term, clip_groups, critic_mse, policy_terms
from bitcomm.learn.precision import update_precision
from bitcomm.learn.rollout import Rollout
from bitcomm.policies.networks import CriticNet, PolicyNet


class DistinctObserved(NamedTuple):
    """A message head of its own (`message_reads` `observed`) over a batch: its input features for each distinct
    observation, `rows (U, w)`, and each agent-step's row among them, `row_of (T, B, n)` (0 at invalid steps). The
    head's layers then run over U rows per pass, not over every agent-step (`bitcomm.learn.distinct`)."""

    rows: torch.Tensor
    row_of: torch.Tensor


class BatchFeatures(NamedTuple):
    """The networks' reading of a batch's observations where it has no parameters (`fixed_features`: every
    encoder but `conv`), computed once per update instead of once per pass: the 4 epochs of the default recipe
    would otherwise sum the same planes 9 times. `policy (T, B, n, flat)`, `critic (T, B, flat)`, 0 at
    invalid steps; None for a network whose encoder learns. `observed`: the message head's distinct inputs, where it
    has a parameter-free head of its own (None: each pass reads the planes)."""

    policy: torch.Tensor | None
    critic: torch.Tensor | None
    observed: DistinctObserved | None = None


class _Forward(NamedTuple):
    """The policy network's pass over the valid steps `(it, ib)` of columns `cols` of a rollout."""

    cols: torch.Tensor
    it: torch.Tensor
    ib: torch.Tensor
    received: torch.Tensor  # (M, n, slots, K)
    encoded: torch.Tensor | None  # (M * n, slots * in_features): the received messages encoded (with a message map)
    feats: torch.Tensor  # (M * n, flat)
    h1: torch.Tensor
    msg_logits: torch.Tensor  # (M * n, out), or (U, out) for the U distinct inputs of a head of its own
    move_logits: torch.Tensor
    msg_rows: torch.Tensor | None  # (M * n,): each step's row of `msg_logits` where those are distinct inputs


class Learner:
    """Policy, critic and their optimizers; `update(rollout)` returns figures for the log."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        task = cfg.task
        self.n = task.env.n_agents
        self.policy = PolicyNet(task, cfg.model)
        self.critic = CriticNet(task, cfg.model, with_message=cfg.estimator == "standard")
        decoder = list(self.policy.message_map.parameters()) if self.policy.message_map is not None else []
        rest = [p for p in self.policy.parameters() if all(p is not d for d in decoder)]
        groups = [{"params": rest}] + ([{"params": decoder, "lr": cfg.map_lr}] if decoder else [])
        # fused: one kernel per step, where foreach's Python bookkeeping is most of a small network's step
        self.opt_policy = torch.optim.Adam(groups, lr=cfg.lr, fused=True)
        self.opt_critic = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr, fused=True)
        self.base_lrs = [[g["lr"] for g in opt.param_groups] for opt in (self.opt_policy, self.opt_critic)]
        self.estimator = get_estimator(cfg.estimator)
        rec = task.recipient_matrix
        self.single_recipient = bool((rec.sum(1) == 1).all())
        # V2 answers a message's own baseline where a message has several recipients (with one it is the
        # recipient's action baseline); the standard estimator reads no message baseline, so V1 is not asked
        self.message_queries = cfg.estimator == "improved" and not self.single_recipient
        self.recipient_of = torch.from_numpy(rec.argmax(1))  # the (first) recipient of each sender
        self.not_recipient = torch.from_numpy(~rec)  # (n, n): [j, k] agent k's action may be given for j's message
        self.slot_senders = torch.from_numpy(task.slot_senders)
        self.observed = torch.tensor(task.env.observed)
        self.slot_goal = self.observed[self.slot_senders.clamp(min=0)]  # (n, slots): whose goal each slot names
        self.routes = Routes(self.slot_senders, self.observed, self.slot_goal, task.channel.delay, task.env.size)
        self.codebook = CodeBook(task.env.size**2, self.policy.head) if cfg.code_coef > 0 else None
        self.progress = 0.0  # of the schedules, as of the last update
        self.move_decay = MoveDecay.from_config(cfg)
        self.senders_wait = SendersWait.from_config(cfg)  # the trainer reads it for the next batch's senders
        self.helper: ThreadPoolExecutor | None = None  # where the critic steps run (bitcomm.learn.beside)

    @property
    def terms(self) -> list[Term]:
        """The objective terms of the policy, from the config (read per step: A3C shares the code book), the
        regularisers scaled down as the budget is played with `anneal_entropy` (all) or `anneal_move_entropy`
        (the move ones; from where `move_decay` starts), each message's and each move's entropy penalised with
        `sharpen_messages` and `sharpen_moves`."""
        message_scale = max(0.0, 1.0 - self.progress) if self.cfg.anneal_entropy else 1.0
        move_scale = self.move_scale if self.cfg.anneal_entropy or self.cfg.anneal_move_entropy else 1.0
        return policy_terms(self.cfg, self.codebook, message_scale, move_scale, self.progress)

    # ---------------------------------------------------------------- critic
    def critic_values(
        self,
        state: torch.Tensor,
        moves: torch.Tensor,
        received: torch.Tensor,
        viewpoint: torch.Tensor,
        given: torch.Tensor,
    ) -> torch.Tensor:
        """V for M samples x k queries: `state (M, 2n, S, S)`, `moves (M, n)`, `received (M, n, slots, K)`,
        `viewpoint (k,)`, `given (k, n)` -> `(M, k)`."""
        return self._values(self.critic.state_features(state), moves, received, viewpoint, given)

    def _values(
        self,
        features: torch.Tensor,
        moves: torch.Tensor,
        received: torch.Tensor,
        viewpoint: torch.Tensor,
        given: torch.Tensor,
    ) -> torch.Tensor:
        """`critic_values` from the critic's state features `(M, flat)`."""
        M, k = features.shape[0], viewpoint.shape[0]
        rep = torch.arange(M).repeat_interleave(k)
        vp = viewpoint.repeat(M)
        rec = received[rep, vp] if self.critic.with_message else None
        v = self.critic.value(features, vp, moves[rep], given.repeat(M, 1), rec)  # each state's k queries in a row
        return v.view(M, k)

    def _state_features(
        self, ro: Rollout, it: torch.Tensor, ib: torch.Tensor, features: BatchFeatures | None
    ) -> torch.Tensor:
        """The critic's features of the state at steps `(it, ib)`: read once per batch where they can be."""
        if features is not None and features.critic is not None:
            return features.critic[it, ib]
        return self.critic.state_features(ro.state[it, ib])

    def _action_queries(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Agent j's action baseline: centred on j, every other action given."""
        return torch.arange(self.n), ~torch.eye(self.n, dtype=torch.bool)

    def _message_queries(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Sender j's message baseline: centred on its first recipient, actions of non-recipients given."""
        return self.recipient_of, self.not_recipient

    @torch.no_grad()
    def baselines(
        self, ro: Rollout, it: torch.Tensor, ib: torch.Tensor, features: BatchFeatures | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        T, B = ro.valid.shape
        state_feats, moves, received = self._state_features(ro, it, ib, features), ro.moves[it, ib], ro.received[it, ib]
        b_action = torch.zeros(T, B, self.n)
        b_action[it, ib] = self._values(state_feats, moves, received, *self._action_queries())
        if self.single_recipient:
            b_message = b_action[:, :, self.recipient_of]
        else:
            b_message = torch.zeros(T, B, self.n)
            if self.message_queries:
                b_message[it, ib] = self._values(state_feats, moves, received, *self._message_queries())
        return b_action, b_message

    def critic_loss(
        self,
        ro: Rollout,
        it: torch.Tensor,
        ib: torch.Tensor,
        returns: torch.Tensor,
        features: BatchFeatures | None = None,
    ) -> torch.Tensor:
        """MSE to Q_t `returns (T, B)` of every query the critic answers (action baselines, plus, for the improved
        estimator, message baselines when a message has several recipients) at the rollout's steps `(it, ib)`."""
        moves, received = ro.moves[it, ib], ro.received[it, ib]
        with update_precision(self.cfg.update_dtype):
            state_feats = self._state_features(ro, it, ib, features)
            values = [self._values(state_feats, moves, received, *self._action_queries())]
            if self.message_queries:
                values.append(self._values(state_feats, moves, received, *self._message_queries()))
        return critic_mse(torch.cat(values, 1).float(), returns[it, ib])

    @torch.no_grad()
    def _policy_reads(self, ro: Rollout) -> tuple[torch.Tensor | None, DistinctObserved | None]:
        """The parameter-free parts of the policy's reading of `ro`, for every pass, from one read of its planes:
        the trunk's features (`BatchFeatures.policy`) and, for a message head of its own, its distinct inputs
        (`BatchFeatures.observed`)."""
        policy = self.policy
        if not policy.fixed_features:
            return None, None
        it, ib = ro.valid.nonzero(as_tuple=True)
        own = policy.message_trunk is not None

        def read(planes: torch.Tensor) -> tuple[torch.Tensor, ...]:
            flat = planes.flatten(0, 1)
            trunk = policy.observation_features(flat, None)
            return (trunk, policy.observed_features(flat)) if own else (trunk,)

        reads = _read_steps(ro.planes, it, ib, read)
        features = _spread(reads[0].view(it.shape[0], self.n, -1), ro.valid, it, ib)
        if not own:
            return features, None
        rows, inverse = distinct_rows(reads[1])
        return features, DistinctObserved(rows, _spread(inverse.view(it.shape[0], self.n), ro.valid, it, ib))

    @torch.no_grad()
    def _critic_features(self, ro: Rollout) -> torch.Tensor | None:
        if not self.critic.fixed_features:
            return None
        it, ib = ro.valid.nonzero(as_tuple=True)
        (features,) = _read_steps(ro.state, it, ib, lambda state: (self.critic.state_features(state),))
        return _spread(features, ro.valid, it, ib)

    def _critic_side(self, ro: Rollout) -> tuple[torch.Tensor | None, Advantages]:
        """The critic's features of `ro` and the advantages from its baselines: what an update needs before its
        first step that the policy's features do not (so a helper thread can read it meanwhile)."""
        with torch.no_grad():  # grad mode is per thread
            critic = self._critic_features(ro)
            return critic, self.advantages(ro, BatchFeatures(None, critic))

    # ---------------------------------------------------------------- update
    @property
    def move_scale(self) -> float:
        """The move regularisers' weight under their decay, as of the last update."""
        return self.move_decay.scale(self.progress)

    def update(
        self,
        ro: Rollout,
        generator: torch.Generator | None = None,
        progress: float = 0.0,
        rolling_length: float | None = None,
    ) -> dict[str, float]:
        """One update on the batch `ro`; `progress` is the fraction of the budget played so far (`anneal_lr`,
        `anneal_entropy`, `anneal_move_entropy`), `rolling_length` the rolling mean training episode length before
        this batch (`move_decay_below`, `senders_wait_below`)."""
        cfg = self.cfg
        self.progress = progress
        self.move_decay.watch(rolling_length, progress)
        self.senders_wait.watch(rolling_length, progress)
        if cfg.anneal_lr:
            for opt, bases in zip((self.opt_policy, self.opt_critic), self.base_lrs, strict=True):
                for group, base in zip(opt.param_groups, bases, strict=True):
                    group["lr"] = base * max(0.0, 1.0 - progress)
        critic_side = start(self.helper, lambda: self._critic_side(ro))  # beside the policy's features
        policy_features, observed = self._policy_reads(ro)
        critic_features, adv = critic_side()
        features = BatchFeatures(policy_features, critic_features, observed)
        B = ro.valid.shape[1]
        stats: dict[str, list[float]] = {}
        clip_scales: list[float] | None = None  # measured on the update's first step, then reused
        for cols, with_critic in minibatch_steps(B, cfg.epochs, cfg.minibatches, cfg.critic_epochs, generator):
            step_stats, clip_scales = self._step(ro, adv, cols, clip_scales, features, with_critic)
            for k, v in step_stats.items():
                stats.setdefault(k, []).append(v)
        if cfg.move_decay_below:
            stats["schedule/move_scale"] = [self.move_scale]
        for k, v in self.senders_wait.figures().items():  # (the a3c trainer logs its main process's watch instead)
            stats[k] = [v]
        return {k: float(np.mean(v)) for k, v in stats.items()}

    def estimated(
        self, ro: Rollout, it: torch.Tensor, ib: torch.Tensor, features: BatchFeatures | None = None
    ) -> Advantages:
        """The estimator's advantages and returns over the critics' baselines, as the estimator computes them:
        before any normalisation or masking (what `studies.variance` compares between the two estimators)."""
        b_action, b_message = self.baselines(ro, it, ib, features)
        batch = EstimatorBatch(ro.rewards, ro.done, ro.valid, b_action, b_message, ro.dropped)
        return self.estimator(batch, self.cfg.gamma, self.cfg.task.channel.delay)

    def advantages(self, ro: Rollout, features: BatchFeatures | None = None) -> Advantages:
        """The chosen estimator's advantages on the batch `ro`, with the critics' baselines (and normalised
        with `adv_norm`): the only weights the policy-gradient term gives the two heads' scores. Messages of the
        episodes whose senders sent their most likely message (`greedy_senders`) get none."""
        it, ib = ro.valid.nonzero(as_tuple=True)
        adv = self.estimated(ro, it, ib, features)
        if self.cfg.adv_norm:
            adv = adv._replace(action=scaled(adv.action, ro.valid), message=scaled(adv.message, ro.valid))
        if ro.sent_greedy.any():  # a most likely message is no sample of the message policy: no credit for it
            adv = adv._replace(message=adv.message.masked_fill(ro.sent_greedy[None, :, None], 0.0))
        return adv

    def _forward(self, ro: Rollout, cols: torch.Tensor, features: BatchFeatures | None = None) -> _Forward:
        """The policy network over every valid step of the episodes in columns `cols`."""
        policy = self.policy
        valid = ro.valid[:, cols]
        it, ib = valid.nonzero(as_tuple=True)
        bc = cols[ib]  # each step's episode, as a column of the rollout
        received = ro.received[it, bc]  # (M, n, slots, K)
        per_agent = received.flatten(0, 1)  # (M * n, slots, K)
        # the dense encoding only for a message map; the trunk reads the bits by the head's own product
        encoded = policy.encode_received(per_agent) if policy.message_map is not None else None

        observed = features.observed if features is not None else None
        with update_precision(self.cfg.update_dtype):  # what the terms compute from these passes is float32
            planes = None
            if features is not None and features.policy is not None:
                feats = features.policy[it, bc].flatten(0, 1)
            else:  # this pass reads the planes itself (`_policy_reads` reads them once where it can)
                planes = ro.planes[it, bc].flatten(0, 1)
                feats = policy.observation_features(planes, encoded)
            h1, h2 = policy.trunk(feats, policy.read_received(per_agent))
            msg_rows = None
            if observed is not None:  # the head's layers over each distinct input of these columns once
                used, msg_rows = torch.unique(observed.row_of[it, bc].flatten(), return_inverse=True)
                msg_logits = policy.message_logits(policy.message_state(None, h2, observed.rows[used]))
            else:
                if planes is None and policy.message_trunk is not None:
                    planes = ro.planes[it, bc].flatten(0, 1)
                msg_logits = policy.message_logits(policy.message_state(planes, h2))
            move_logits = policy.move_logits(h2)
        feats, h1, msg_logits, move_logits = (x.float() for x in (feats, h1, msg_logits, move_logits))
        return _Forward(cols, it, ib, received, encoded, feats, h1, msg_logits, move_logits, msg_rows)

    def _batch(self, ro: Rollout, fw: _Forward, adv: Advantages | None = None) -> StepBatch:
        return StepBatch(
            ro, adv, fw.cols, fw.it, fw.ib, fw.received, fw.encoded, fw.feats, fw.h1, fw.msg_logits, fw.move_logits,
            self.policy, self.routes, fw.msg_rows,
        )  # fmt: skip

    def log_probs(self, ro: Rollout, fw: _Forward | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Differentiable `(T, Bc, n)` log pi(a_t) and log Pm(m_t) of the moves and messages the rollout
        sampled, over the columns of the pass `fw` (default: one over the whole rollout); 0 where invalid."""
        if fw is None:
            fw = self._forward(ro, torch.arange(ro.valid.shape[1]))
        return self._batch(ro, fw).log_probs

    def _step(
        self,
        ro: Rollout,
        adv: Advantages,
        cols: torch.Tensor,
        clip_scales: list[float] | None,
        features: BatchFeatures | None = None,
        with_critic: bool = True,
    ) -> tuple[dict[str, float], list[float]]:
        """One gradient step of the policy, and of the critic `with_critic`, on the whole episodes in columns `cols`;
        returns the figures for the log and the policy losses' clip factors (see `_clipped_step`)."""
        fw = self._forward(ro, cols, features)

        def critic_step() -> float:  # regress on Q_t for every query the critic answers
            v_loss = self.critic_loss(ro, fw.it, cols[fw.ib], adv.returns, features)
            self._clipped_step(self.opt_critic, list(self.critic.parameters()), [v_loss], None)
            return v_loss.item()

        critic_loss = start(self.helper, critic_step) if with_critic else None  # beside the policy's step
        # policy: the recipe's terms, summed per clip group (reinforcement, then each auxiliary term)
        losses, out = clip_groups(self.terms, self._batch(ro, fw, adv))
        clip_scales = self._clipped_step(self.opt_policy, list(self.policy.parameters()), losses, clip_scales)
        if critic_loss is not None:
            out["losses/value"] = critic_loss()
        return out, clip_scales

    def _clipped_step(
        self,
        opt: torch.optim.Optimizer,
        params: list[torch.nn.Parameter],
        losses: list[torch.Tensor],
        scales: list[float] | None,
    ) -> list[float]:
        """Clip each loss's gradient to `max_grad_norm` on its own, then step on their sum, so an
        auxiliary loss is neither drowned by the policy gradient nor drowns it (one global clip does:
        docs/tuning.md). Measuring the factors takes a backward pass per loss; given `scales` (the
        factors an earlier step of the same batch measured), one backward pass of the weighted sum
        makes the same step at the cost of one. Returns the factors used."""
        if scales is None or len(losses) == 1:
            total: list[torch.Tensor | None] = [None] * len(params)
            scales = []
            for k, loss in enumerate(losses):
                grads = torch.autograd.grad(loss, params, retain_graph=k < len(losses) - 1, allow_unused=True)
                present = [g for g in grads if g is not None]
                scales.append(min(1.0, self.cfg.max_grad_norm / (float(torch.nn.utils.get_total_norm(present)) + 1e-6)))
                if scales[k] < 1.0:  # one call for every tensor: a small network's step is mostly per-call costs
                    torch._foreach_mul_(present, scales[k])
                total = [t if g is None else (g if t is None else t + g) for t, g in zip(total, grads, strict=True)]
        else:
            weighted = torch.stack([loss * scale for loss, scale in zip(losses, scales, strict=True)]).sum()
            total = list(torch.autograd.grad(weighted, params, allow_unused=True))
        for p, g in zip(params, total, strict=True):
            p.grad = g
        opt.step()
        return scales


def minibatch_steps(
    episodes: int, epochs: int, minibatches: int, critic_epochs: int, generator: torch.Generator | None
) -> Iterator[tuple[torch.Tensor, bool]]:
    """The columns of each gradient step of an update over a batch of `episodes`, `epochs` passes of `minibatches`
    whole-episode minibatches (shuffled by `generator` where there are several), and whether the critics step with it:
    in the first `critic_epochs` passes only (0: every pass, `critic_passes`). The grid's and the wrapped env's
    learners step alike."""
    critic = critic_passes(critic_epochs, epochs)
    for epoch in range(epochs):
        order = torch.randperm(episodes, generator=generator) if minibatches > 1 else torch.arange(episodes)
        for cols in order.chunk(minibatches):
            yield cols, epoch < critic


CHUNK_ELEMENTS = 1 << 18
"""`_read_steps` reads about this many plane entries at a time: 1 MiB as float32, so that the floats an encoder
makes of a chunk's bytes are summed while they are in the cache."""


def _read_steps(
    x: torch.Tensor, it: torch.Tensor, ib: torch.Tensor, read: Callable[[torch.Tensor], tuple[torch.Tensor, ...]]
) -> tuple[torch.Tensor, ...]:
    """`read(x[it, ib])` for `(T, B, ...)` observations, in chunks of steps along `it, ib`, each of its outputs'
    rows concatenated: a 32x32 batch's planes are 30 MB as bytes and four times that as floats, and converting them
    whole (then summing) cost about twice what it costs chunk by chunk."""
    chunk = max(1, CHUNK_ELEMENTS // max(1, x[0, 0].numel()))
    reads = [read(x[t, b]) for t, b in zip(it.split(chunk), ib.split(chunk), strict=True)]
    return tuple(torch.cat(parts) for parts in zip(*reads, strict=True))


def _spread(x: torch.Tensor, valid: torch.Tensor, it: torch.Tensor, ib: torch.Tensor) -> torch.Tensor:
    """`(M, ...)` values at the valid steps `(it, ib)` -> `(T, B, ...)`, 0 elsewhere."""
    out = x.new_zeros(*valid.shape, *x.shape[1:])
    out[it, ib] = x
    return out


def scaled(a: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """`a` divided by the standard deviation of its entries where `valid` (unchanged when that is not finite, or
    when fewer than two entries are valid, where torch's `std` warns and gives NaN: every agent's action fixed by
    `fixed_actions` leaves no action advantage): `adv_norm`, for the grid's learner and the wrapped-env learner
    alike."""
    values = a[valid]
    if values.numel() < 2:
        return a
    std = values.std()
    return a / (std + 1e-8) if torch.isfinite(std) else a
