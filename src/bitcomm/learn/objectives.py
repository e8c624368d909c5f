"""The objective terms of one learning step, each a small function of the minibatch with its maths below.

A recipe of terms (`policy_terms(cfg, n)`) is what the learner minimises; the update only sums the
terms of each clip group, clips each group to `max_grad_norm` on its own, and steps
(`Learner._clipped_step`). Notation, per valid step `t` of episode `b`, for agent `j` of `n`:
`pi` the move policy, `Pm` the message distribution of the head, `A` the estimator's advantages
(`bitcomm.learn.estimators`, detached), `H` an entropy, `V` a critic value, `Q_t` the return.

Reinforcement (SPEC section 7; every gradient reaching a policy head comes from these):

    PolicyGradient   -(1/#valid) sum_{t,b,j} [log pi(a) A^a + log Pm(m) A^m]        (clip = 0)
                     -(1/#valid) sum_{t,b,j} sum_{head} min(r A, clip(r, 1-e, 1+e) A),  r = pi/pi_old
    Entropy move     -n w mean H(pi)          (mean over agent-steps; n puts it on the summed scale)
    Entropy message  -n w mean H(Pm)
    Marginal message -n w H(mean Pm): the entropy of the minibatch's average message distribution, a bonus
                     for states that use different messages (`entropy_message_marginal`, off by default)
    Nearby divergence -n w mean_{g, g'} JS(Pm(. | g), Pm(. | g')) over pairs of goal cells at most r apart: a
                     bonus for telling nearby goals apart (`message_divergence`; a head that reads only the goal)
    Logit decay      n w mean_g mean_k logit_k(g)^2 over every goal cell g: a pull of the message logits toward 0
                     that, unlike an entropy, does not fade as a word saturates (`message_logit_decay`; a head that
                     reads only the goal)
    UniformMove      -n w mean_a log pi(a) = n w (KL(U || pi) + log 5): an entropy-type pull toward
                     uniform moves that, unlike H, grows without bound as a move's probability falls

Critic (its own optimizer, and its own clip group): `critic_mse`, mean (V - Q_t)^2.

Auxiliary (off by default, never in a pure run; each its own clip group, so it neither drowns the
policy gradient nor is drowned by it). They read the grid task's goals, so they are specific to it:

    GoalTerm   the receiver names its own goal cell from what it heard (or, with the message map,
               each slot's map names the goal its sender observes): cross-entropy, weight `goal_coef`
    SeenTerm   the sender names the goal it observes from its first hidden layer (`seen_coef`)
    CodeTerm   the sender says its goal's code word (`bitcomm.learn.codebook`): -log Pm(word) (`code_coef`)

A term returns its weighted loss and the figures it logs. Terms are evaluated in recipe order, which
is also the order the network's pieces are built in (the log-softmax of the moves is shared), so a
run's numbers do not depend on how the terms are grouped.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import torch
import torch.nn.functional as F

from bitcomm.learn.codebook import CodeBook
from bitcomm.learn.config import TrainConfig
from bitcomm.learn.estimators import Advantages, policy_gradient_loss
from bitcomm.learn.rollout import Rollout
from bitcomm.policies.heads import marginal_entropy, pair_divergence, probabilities, row_weights
from bitcomm.policies.networks import OBSERVED_PLANE, PolicyNet

NEARBY_PAIRS_PER_STEP = 1024
"""At most this many pairs of nearby goals enter one step's `NearbyMessageDivergence` (a uniform draw of them
where the grid has more): each pair costs a row of all 2^K message probabilities."""


class Routes(NamedTuple):
    """Who talks to whom in the task, for the auxiliary terms: `slot_senders (n, slots)` (-1: none),
    `observed (n,)` whose goal each agent sees, `slot_goal (n, slots)` whose goal each slot names."""

    slot_senders: torch.Tensor
    observed: torch.Tensor
    slot_goal: torch.Tensor
    delay: int
    size: int


class StepBatch:
    """One minibatch: the policy's pass over the valid steps `(it, ib)` of columns `cols` of a rollout,
    the advantages of those columns, and what the terms derive from them (computed once, on first use)."""

    def __init__(
        self,
        ro: Rollout,
        adv: Advantages | None,
        cols: torch.Tensor,
        it: torch.Tensor,
        ib: torch.Tensor,
        received: torch.Tensor,
        encoded: torch.Tensor | None,
        feats: torch.Tensor,
        h1: torch.Tensor,
        msg_logits: torch.Tensor,
        move_logits: torch.Tensor,
        policy: PolicyNet,
        routes: Routes,
        msg_rows: torch.Tensor | None = None,
    ) -> None:
        self.ro, self.adv, self.cols, self.it, self.ib = ro, adv, cols, it, ib
        self.received = received  # (M, n, slots, K)
        self.encoded = encoded  # (M * n, slots * in_features): the received messages encoded (with a message map)
        self.feats = feats  # (M * n, flat)
        self.h1 = h1
        self.move_logits = move_logits  # (M * n, 5)
        # the message logits of each step (M * n, out), or of each distinct input (U, out) and each step's row
        # among them, `msg_rows (M * n,)`: the message terms then work over the U rows
        self.distinct_msg_logits, self.msg_rows = msg_logits, msg_rows
        self.policy, self.routes = policy, routes
        self.n = ro.moves.shape[2]

    @functools.cached_property
    def msg_logits(self) -> torch.Tensor:
        """`(M * n, out)` message logits of each valid step's agents."""
        rows = self.msg_rows
        return self.distinct_msg_logits if rows is None else self.distinct_msg_logits[rows]

    @functools.cached_property
    def msg_weights(self) -> torch.Tensor | None:
        """Each distinct message input's share of the steps (None: one row per step)."""
        rows = self.msg_rows
        return None if rows is None else row_weights(rows, self.distinct_msg_logits.shape[0])

    @functools.cached_property
    def at(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The valid steps as indices into the rollout's `(T, B, ...)` arrays: `(it, cols[ib])`."""
        return self.it, self.cols[self.ib]

    @functools.cached_property
    def step_log_probs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Differentiable `(M, n)` log pi(a_t) and log Pm(m_t) of what the rollout sampled, at the valid steps."""
        M, n = self.it.shape[0], self.n
        logp_move = self.move_log_softmax.gather(-1, self.ro.moves[self.at].view(-1, 1)).view(M, n)
        return logp_move, self.msg_log_prob_and_entropy[0].view(M, n)

    @functools.cached_property
    def log_probs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """`step_log_probs` in the rollout's layout: `(T, Bc, n)`, 0 where invalid."""

        def full(x: torch.Tensor) -> torch.Tensor:  # (M, n) sample values -> (T, Bc, n)
            out = torch.zeros(self.ro.valid.shape[0], self.cols.shape[0], self.n, dtype=x.dtype)
            out[self.it, self.ib] = x
            return out

        logp_move, logp_msg = self.step_log_probs
        return full(logp_move), full(logp_msg)

    @functools.cached_property
    def msg_log_prob_and_entropy(self) -> tuple[torch.Tensor, torch.Tensor]:
        """`(M * n,)` log Pm(m_t) of the sent messages and the entropy of Pm, computed together (one-hot: from
        one log-softmax, see `OneHotHead.log_prob_and_entropy`)."""
        bits = self.ro.bits[self.at].flatten(0, 1)
        if self.msg_rows is None:
            return self.policy.head.log_prob_and_entropy(self.msg_logits, bits)
        return self.policy.head.log_prob_and_entropy_of_rows(self.distinct_msg_logits, self.msg_rows, bits)

    @functools.cached_property
    def step_advantages(self) -> Advantages:
        """The advantages at the valid steps: `(M, n)` (returns `(M,)`)."""
        a, at = self.adv, self.at
        if a is None:
            raise ValueError("this batch was built without advantages")
        return Advantages(a.action[at], a.message[at], a.returns[at])

    @functools.cached_property
    def move_log_softmax(self) -> torch.Tensor:
        """`(M * n, 5)` log pi over all moves, shared by the entropy-type terms."""
        return torch.log_softmax(self.move_logits, -1)

    @functools.cached_property
    def goal_message_logits(self) -> torch.Tensor:
        """`(S^2, out)` message logits of every goal cell, for a message head that reads only the goal its sender
        observes: one pass of the head's layers shared by the terms over goal cells (the nearby goals' divergence and
        the logit decay), where each ran its own (0.91x the throughput for the decay's, session 56)."""
        return self.policy.observed_message_logits(goal_planes(self.routes.size))

    @functools.cached_property
    def goal(self) -> torch.Tensor:
        """`(M, n)` each agent's own goal cell at each step (privileged: auxiliary terms only)."""
        return self.ro.goal[self.at[1]]


class Term(Protocol):
    """One named piece of the objective: `term(batch) -> (weighted loss, figures for the log)`."""

    @property
    def name(self) -> str: ...
    @property
    def auxiliary(self) -> bool:
        """True: its own clip group, and off in a pure run."""
        ...

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]: ...


# ------------------------------------------------------------------------------------------------ reinforcement
def clipped_policy_loss(
    logp_action: torch.Tensor,
    logp_message: torch.Tensor,
    old_action: torch.Tensor,
    old_message: torch.Tensor,
    adv: Advantages,
    valid: torch.Tensor,
    clip: float,
) -> torch.Tensor:
    """PPO's clipped surrogate, applied to the action and message parts with their own advantages; any layout
    `(..., n)` with `valid (...)`, as `policy_gradient_loss`."""

    def part(logp: torch.Tensor, old: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        ratio = torch.exp(logp - old)
        most = torch.finfo(ratio.dtype).max  # a wider clip (--clip 1e300: none) is no float32 bound, a RuntimeError
        return torch.minimum(ratio * a, ratio.clamp(max(1 - clip, -most), min(1 + clip, most)) * a)

    per_step = (part(logp_action, old_action, adv.action) + part(logp_message, old_message, adv.message)).sum(-1)
    return -torch.where(valid, per_step, 0.0).sum() / valid.sum().clamp(min=1)


@dataclass(frozen=True)
class PolicyGradient:
    """The estimator's term, per head: each head's log-probability weighted by its own advantage
    (`bitcomm.learn.estimators.policy_gradient_loss`), or PPO's clipped surrogate when `clip > 0`."""

    clip: float = 0.0
    name: str = "policy_gradient"
    auxiliary: bool = False

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        logp_move, logp_msg = b.step_log_probs  # at the valid steps only: every one of them counts
        adv, every = b.step_advantages, torch.ones(logp_move.shape[0], dtype=torch.bool)
        if self.clip > 0:
            old_move, old_msg = b.ro.logp_move[b.at], b.ro.logp_message[b.at]
            pg = clipped_policy_loss(logp_move, logp_msg, old_move, old_msg, adv, every, self.clip)
        else:
            pg = policy_gradient_loss(logp_move, logp_msg, adv, every)
        return pg, {"losses/policy": pg.item()}


@dataclass(frozen=True)
class Entropy:
    """-n w mean H: the entropy bonus of one head, `move` (H(pi)) or `message` (H(Pm), as the head computes
    it); logged even at weight 0, as `charts/entropy_<head>`."""

    head: str
    weight: float
    auxiliary: bool = False

    @property
    def name(self) -> str:
        return f"entropy_{self.head}"

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        if self.head == "move":
            logp = b.move_log_softmax
            h = -(probabilities(logp) * logp).sum(-1).mean()
        else:
            h = b.msg_log_prob_and_entropy[1].mean()
        return -(b.n * (self.weight * h)), {f"charts/{self.name}": h.item()}


@dataclass(frozen=True)
class MarginalMessageEntropy:
    """-n w H(mean Pm): the entropy of the average, over the minibatch's agent-steps, of the message
    distribution (`bitcomm.policies.heads.marginal_entropy`); logged as `charts/entropy_message_marginal`."""

    weight: float
    name: str = "entropy_message_marginal"
    auxiliary: bool = False

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        h = marginal_entropy(b.policy.head, b.distinct_msg_logits, b.msg_weights)
        return -(b.n * self.weight) * h, {f"charts/{self.name}": h.item()}


@functools.cache
def goal_planes(size: int) -> torch.Tensor:
    """An observation of each goal cell `(S^2, 2, S, S)`: its observed plane, which is all a head that reads only
    that plane reads."""
    cells = torch.arange(size * size)
    planes = torch.zeros(size * size, 2, size, size)
    planes[cells, OBSERVED_PLANE, cells // size, cells % size] = 1.0
    return planes


@functools.cache
def nearby_goals(size: int, radius: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`goal_planes(size)`, and every pair of goal cells at most `radius` apart (Manhattan), each once: `(P,)`,
    `(P,)`."""
    cells = torch.arange(size * size)
    row, col = cells // size, cells % size
    apart = (row[:, None] - row[None]).abs() + (col[:, None] - col[None]).abs()
    first, second = torch.nonzero((apart <= radius) & (cells[:, None] < cells[None]), as_tuple=True)
    return goal_planes(size), first, second


@dataclass(frozen=True)
class NearbyMessageDivergence:
    """-n w mean JS(Pm(. | g), Pm(. | g')) over pairs of goal cells g, g' at most `radius` apart, of a message head
    that reads only the goal its sender observes (`TrainConfig.message_divergence`); logged as
    `charts/message_divergence`."""

    weight: float
    radius: int
    name: str = "message_divergence"
    auxiliary: bool = False

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        _, first, second = nearby_goals(b.routes.size, self.radius)
        if first.shape[0] > NEARBY_PAIRS_PER_STEP:
            drawn = torch.randperm(first.shape[0])[:NEARBY_PAIRS_PER_STEP]
            first, second = first[drawn], second[drawn]
        js = pair_divergence(b.policy.head, b.goal_message_logits, first, second).mean()
        return -(b.n * self.weight) * js, {f"charts/{self.name}": js.item()}


@dataclass(frozen=True)
class MessageLogitDecay:
    """n w mean_g mean_k logit_k(g)^2 over every goal cell g's message logits, of a message head that reads only the
    goal its sender observes (`TrainConfig.message_logit_decay`); logs the mean |logit| as
    `charts/message_logit_abs`."""

    weight: float
    name: str = "message_logit_decay"
    auxiliary: bool = False

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        logits = b.goal_message_logits
        return (b.n * self.weight) * logits.square().mean(), {"charts/message_logit_abs": logits.abs().mean().item()}


@dataclass(frozen=True)
class UniformMove:
    """-n w mean_a log pi(a) = n w (KL(U || pi) + log 5), U uniform over the 5 moves."""

    weight: float
    name: str = "uniform_move"
    auxiliary: bool = False

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        return -(b.n * self.weight) * b.move_log_softmax.mean(), {}


def critic_mse(values: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """The critic term: mean over samples and queries of (V - Q_t)^2; `values (M, k)`, `returns (M,)`."""
    return F.mse_loss(values, returns[:, None].expand_as(values))


# ------------------------------------------------------------------------------------------------ auxiliary
def cell_loss(logits: torch.Tensor, cell: torch.Tensor, size: int) -> torch.Tensor:
    """Cross-entropy of row and column read-outs `(N, 2 * size)` against cell indices `(N,)`."""
    return F.cross_entropy(logits[:, :size], cell // size) + F.cross_entropy(logits[:, size:], cell % size)


def message_sources(b: StepBatch) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
    """For each received slot `(M, n, slots)`: the index of the step, episode and sender that sent it
    (into arrays over columns `cols`), and whether a message arrived there (sent, in time, not dropped)."""
    d, senders = b.routes.delay, b.routes.slot_senders
    ts = (b.it - d).clamp(min=0)[:, None, None]
    snd = senders.clamp(min=0)[None]  # (1, n, slots)
    src = ts, b.ib[:, None, None], snd
    use = (b.it >= d)[:, None, None] & (senders >= 0)[None] & ~b.ro.dropped[:, b.cols][src]
    return src, use


def heard(b: StepBatch, noise: float) -> torch.Tensor:
    """Receivers' inputs as a differentiable function of senders' logits (see TrainConfig.channel_noise)."""
    ro, cols, it, ib, head = b.ro, b.cols, b.it, b.ib, b.policy.head
    T, Bc = ro.valid.shape[0], cols.shape[0]
    logits = torch.zeros(T, Bc, b.n, b.msg_logits.shape[-1])
    logits[it, ib] = b.msg_logits.view(it.shape[0], b.n, -1)
    src, use = message_sources(b)
    sent_bits = ro.bits[:, cols][src]  # (M, n, slots, K)
    flips = b.received ^ sent_bits
    if noise > 0:
        soft = head.relaxed(logits[src], flips, noise)
    else:
        soft = head.straight_through(logits[src], b.received, flips)
    return torch.where(use[..., None], soft, head.encode(b.received)).flatten(0, 1).flatten(1)


@dataclass(frozen=True)
class GoalTerm:
    """Auxiliary (privileged): w * cross-entropy of the goal a receiver should know. With the message map,
    each slot's map names the goal its sender observes, read from the bits that arrived (mean over slots
    where a message arrived); without it, the receiver names its own goal from what it heard, through a
    relaxed channel (`channel_noise`), so the gradient reaches the sender."""

    weight: float
    channel_noise: float
    name: str = "goal"
    auxiliary: bool = True

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        policy, goal, size = b.policy, b.goal, b.routes.size
        if policy.message_map is not None:
            _, present = message_sources(b)
            label = goal[:, b.routes.slot_goal].flatten()
            assert b.encoded is not None, "a message map's pass encodes the received messages"
            ce = F.cross_entropy(policy.map_logits(b.encoded).flatten(0, 1), label, reduction="none")
            mask = present.flatten().float()
            loss = (ce * mask).sum() / mask.sum().clamp(min=1)
        else:
            h1_heard, _ = policy.trunk(b.feats, policy.message_in(heard(b, self.channel_noise)))
            loss = cell_loss(policy.goal_logits(h1_heard), goal.flatten(), size)
        return self.weight * loss, {"losses/goal": loss.item()}


@dataclass(frozen=True)
class SeenTerm:
    """Auxiliary (privileged): w * cross-entropy of the sender naming the goal it observes, from its first
    hidden layer."""

    weight: float
    name: str = "seen"
    auxiliary: bool = True

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        seen_goal = b.goal[:, b.routes.observed].flatten()
        loss = cell_loss(b.policy.seen_logits(b.h1), seen_goal, b.routes.size)
        return self.weight * loss, {"losses/seen": loss.item()}


@dataclass(frozen=True)
class CodeTerm:
    """Auxiliary (privileged): -w mean log Pm(word), the word the code book assigns the sender's goal."""

    weight: float
    codebook: CodeBook
    name: str = "code"
    auxiliary: bool = True

    def __call__(self, b: StepBatch) -> tuple[torch.Tensor, dict[str, float]]:
        seen_goal = b.goal[:, b.routes.observed].flatten()
        words = self.codebook.targets(seen_goal, b.msg_logits)
        loss = -b.policy.head.log_prob(b.msg_logits, words).mean()
        return self.weight * loss, {"losses/code": loss.item()}


# ------------------------------------------------------------------------------------------------ recipe
def policy_terms(
    cfg: TrainConfig,
    codebook: CodeBook | None,
    message_scale: float = 1.0,
    move_scale: float = 1.0,
    progress: float = 0.0,
) -> list[Term]:
    """The terms `cfg` asks for, in the order they are evaluated: the reinforcement terms (the entropy
    bonuses always, for their figures; the message bonuses weighted by `message_scale` times the config's
    weight, less `sharpen_messages` times the schedule's `progress` for each message's entropy; the move bonus
    and the uniform-move pull by `move_scale`, the move bonus less `sharpen_moves` times `progress`), then each
    auxiliary term whose weight is positive."""
    terms: list[Term] = [
        PolicyGradient(cfg.clip),
        Entropy("move", cfg.entropy_move * move_scale - cfg.sharpen_moves * progress),
        Entropy("message", cfg.entropy_message * message_scale - cfg.sharpen_messages * progress),
    ]
    if cfg.entropy_message_marginal > 0:
        terms.append(MarginalMessageEntropy(cfg.entropy_message_marginal * message_scale))
    if cfg.message_divergence > 0:
        terms.append(NearbyMessageDivergence(cfg.message_divergence * message_scale, cfg.message_divergence_radius))
    if cfg.message_logit_decay > 0:
        terms.append(MessageLogitDecay(cfg.message_logit_decay * message_scale))
    if cfg.uniform_move > 0:
        terms.append(UniformMove(cfg.uniform_move * move_scale))
    if cfg.goal_coef > 0:
        terms.append(GoalTerm(cfg.goal_coef, cfg.channel_noise))
    if cfg.seen_coef > 0:
        terms.append(SeenTerm(cfg.seen_coef))
    if codebook is not None:
        terms.append(CodeTerm(cfg.code_coef, codebook))
    return terms


def clip_groups(terms: list[Term], b: StepBatch) -> tuple[list[torch.Tensor], dict[str, float]]:
    """Evaluate `terms` on `b`: the sum of the reinforcement terms first, then each auxiliary term as a
    group of its own; and every term's figures, auxiliary first (the log's column order)."""
    main: list[torch.Tensor] = []
    auxiliary: list[torch.Tensor] = []
    figures: dict[str, float] = {}
    aux_figures: dict[str, float] = {}
    for term in terms:
        loss, logged = term(b)
        (auxiliary if term.auxiliary else main).append(loss)
        (aux_figures if term.auxiliary else figures).update(logged)
    return [functools.reduce(torch.add, main), *auxiliary], {**aux_figures, **figures}
