"""The two policy-gradient estimators of SPEC section 4 (paper eq. 7 and 8), as pure functions.

Each estimator maps a batch of trajectory tensors to *advantages*: the weights of
`grad log pi_j(a_t^j)` and `grad log Pm_j(m_t^j)` in agent j's gradient. The trainer (A3C or the
synchronous mode) builds its loss from them with `policy_gradient_loss`, so the maths lives here once.

Shapes: T steps, B episode columns, n agents. A column may hold several episodes one after the
other (`done` ends one, the next step starts the next) and padding (`valid` false) after the last.
Returns are Monte Carlo: they never bootstrap past `done`, an invalid step or the end of the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from bitcomm.errors import bad_value


class EstimatorBatch(NamedTuple):
    """What an estimator reads from a rollout; baselines come from the critics (SPEC section 3)."""

    rewards: torch.Tensor
    """(T, B) float: team reward R_t of step t."""
    done: torch.Tensor
    """(T, B) bool: the episode ends after step t (terminated or truncated)."""
    valid: torch.Tensor
    """(T, B) bool: step t exists (false on padding after an episode's end)."""
    baseline_action: torch.Tensor
    """(T, B, n) float: standard: V1(s_t, a_t^{-j}, m_{t-1}^{-j}); improved: V2(s_t, a_t^{-j})."""
    baseline_message: torch.Tensor
    """(T, B, n) float, improved only: V2(s_t, actions of the agents not among j's recipients), the
    baseline of the message of sender j that arrives at step t. Two agents: baseline_action[t, :, x]."""
    dropped: torch.Tensor
    """(T, B, n) bool: the channel dropped the message j sent at step t (for every recipient)."""


class Advantages(NamedTuple):
    """Per-step, per-agent weights of the score functions; zero at invalid steps."""

    action: torch.Tensor
    """(T, B, n): multiplies grad log pi_j(a_t^j)."""
    message: torch.Tensor
    """(T, B, n): multiplies grad log Pm_j(m_t^j)."""
    returns: torch.Tensor
    """(T, B): Monte Carlo Q_t, the critics' regression target."""


def discounted_returns(rewards: torch.Tensor, done: torch.Tensor, valid: torch.Tensor, gamma: float) -> torch.Tensor:
    """Q_t = sum_{k=t..end of t's episode} gamma^(k-t) R_k; 0 at invalid steps.

    Backward recursion Q_t = R_t + gamma * Q_{t+1} * [not done_t]; an invalid step has Q = 0, so
    padding and the end of the batch also cut the sum.
    """
    q = torch.zeros_like(rewards)
    nxt = torch.zeros_like(rewards[0])
    for t in range(rewards.shape[0] - 1, -1, -1):
        nxt = torch.where(valid[t], rewards[t] + gamma * torch.where(done[t], 0.0, nxt), 0.0)
        q[t] = nxt
    return q


def _check_batch(batch: EstimatorBatch, delay: int, per_agent: tuple[str, ...]) -> None:
    """Fail early, naming the field, rather than broadcast a wrong shape into silent nonsense."""
    if isinstance(delay, bool) or not isinstance(delay, int) or delay < 1:
        raise bad_value("delay", delay, "an integer >= 1")
    t, b = batch.rewards.shape
    for name in ("done", "valid"):
        shape = tuple(getattr(batch, name).shape)
        if shape != (t, b):
            raise bad_value(f"{name}.shape", shape, f"must be (T, B) = {(t, b)}")
    n = batch.baseline_action.shape[-1]
    for name in per_agent:
        shape = tuple(getattr(batch, name).shape)
        if shape != (t, b, n):
            raise bad_value(f"{name}.shape", shape, f"must be (T, B, n) = {(t, b, n)}")


def standard(batch: EstimatorBatch, gamma: float, delay: int) -> Advantages:
    """Paper eq. 7: action and message share the advantage Q_t - V1(s_t, a_t^{-j}, m_{t-1}^{-j}).

    `baseline_message`, `dropped` and `delay` are not used: the standard estimator treats a message
    like an action that may change everything after it (delay is still checked, for symmetry).
    """
    _check_batch(batch, delay, ("baseline_action",))
    q = discounted_returns(batch.rewards, batch.done, batch.valid, gamma)
    adv = torch.where(batch.valid[..., None], q[..., None] - batch.baseline_action, 0.0)
    return Advantages(action=adv, message=adv.clone(), returns=q)


def improved(batch: EstimatorBatch, gamma: float, delay: int) -> Advantages:
    """Paper eq. 8 with delay d (SPEC section 4): a message is judged by the recipients' action on arrival.

    action[t, j]  = Q_t - V2(s_t, a_t^{-j})
    message[t, j] = gamma^d * (Q_{t+d} - V2(s_{t+d}, a_{t+d}^{not recipients of j}))
                    if step t+d is valid and in t's episode and the message was not dropped, else 0.
    The message cannot change rewards before t+d, nor anything if it arrives after the end or is
    lost, so those parts may be absorbed by its baseline without bias (paper III-B).
    """
    _check_batch(batch, delay, ("baseline_action", "baseline_message", "dropped"))
    q = discounted_returns(batch.rewards, batch.done, batch.valid, gamma)
    valid = batch.valid
    action = torch.where(valid[..., None], q[..., None] - batch.baseline_action, 0.0)
    message = torch.zeros_like(action)
    d = delay
    if d < q.shape[0]:
        # Episode segment index: number of episode ends (done or invalid) strictly before step t.
        cut = (batch.done | ~valid).long()
        seg = torch.cumsum(cut, 0) - cut
        # Step t + d is in t's episode iff no cut in t..t+d-1 (which also implies t is valid).
        arrives = (seg[d:] == seg[:-d]) & valid[d:]
        credit = arrives[..., None] & ~batch.dropped[:-d]
        late = gamma**d * (q[d:, :, None] - batch.baseline_message[d:])
        message[:-d] = torch.where(credit, late, 0.0)
    return Advantages(action=action, message=message, returns=q)


Estimator = Callable[[EstimatorBatch, float, int], Advantages]

ESTIMATORS: dict[str, Estimator] = {"standard": standard, "improved": improved}


def get_estimator(name: str) -> Estimator:
    """The estimator registered under `name`; a ConfigError names the value otherwise."""
    try:
        return ESTIMATORS[name]
    except (KeyError, TypeError):
        raise bad_value("estimator", name, "choose one of " + ", ".join(ESTIMATORS)) from None


def policy_gradient_loss(
    logp_action: torch.Tensor, logp_message: torch.Tensor, adv: Advantages, valid: torch.Tensor
) -> torch.Tensor:
    """Scalar to minimise: -(1/#valid (t,b)) sum_{valid t,b} sum_j [log pi_j(a) A^a + log Pm_j(m) A^m].

    `logp_*` are (T, B, n) log-probabilities of the sampled actions and messages (or any `(..., n)` with `valid
    (...)`: the learner passes its minibatch's valid steps alone, `(M, n)`). Advantages are
    detached, so the critics' baselines get no gradient from here. Agents share parameters: summing
    over j adds every agent's samples to the same gradient (SPEC section 4).
    """
    per_step = (logp_action * adv.action.detach() + logp_message * adv.message.detach()).sum(-1)
    per_step = torch.where(valid, per_step, 0.0)
    return -per_step.sum() / valid.sum().clamp(min=1)
