"""One learning update on a batch of whole episodes of a wrapped env (SPEC sections 4, 7 and 8).

# baselines  the critic once per batch: V1 (standard) or V2 (improved), from each agent's viewpoint with every
#            other action given, and (improved) from each recipient's viewpoint for every sender's message,
#            the recipients' actions masked
# advantages `estimators.standard` / `estimators.improved`, with multi-recipient credit (below)
# update     per minibatch: policy gradient (plain or PPO-clipped, `objectives.clipped_policy_loss`) plus the
#            two entropy bonuses, one clipped policy step; then one critic step on `critic_mse`

Multi-recipient credit (SPEC section 8). A message sent by j at t is credited with
    gamma^d * sum over recipients r of j, present at t + d, of (Q_{t+d} - V2_r(s_{t+d}, a^{not recipients of j}))
(0 with no recipient, if it was dropped, or if it arrives after the episode). `improved` computes one
recipient's term, `gamma^d (Q_{t+d} - baseline)` with the arrival and drop rules; it runs once per recipient
rank k (the k-th recipient of every sender at once), with the message counted as lost where that recipient
does not exist or is absent at t + d, and the terms are summed. The policy heads get only these
policy-gradient terms and the entropy terms: the run is pure (SPEC section 7). Agents whose inner action the
wrapper fixes (`fixed_actions`) add no action log-probability and no action entropy.
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from bitcomm.config import slot_table
from bitcomm.envs.vector import EnvLayout
from bitcomm.learn.beside import start
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.learn.env_rollout import EnvRollout
from bitcomm.learn.estimators import Advantages, EstimatorBatch, get_estimator, policy_gradient_loss
from bitcomm.learn.learner import minibatch_steps, scaled
from bitcomm.learn.objectives import clipped_policy_loss, critic_mse
from bitcomm.policies.heads import marginal_entropy
from bitcomm.policies.mlp import MlpCritic, MlpPolicy


class EnvLearner:
    """Policy, critic and their optimizers for one wrapped env; `update(rollout)` returns figures for the log."""

    def __init__(self, cfg: EnvTrainConfig, layout: EnvLayout) -> None:
        self.cfg, self.layout, self.n = cfg, layout, layout.n
        self.policy = MlpPolicy(layout, cfg.messages, cfg.hidden, cfg.obs_norm)
        self.critic = MlpCritic(layout, cfg.messages, cfg.hidden, cfg.estimator == "standard", cfg.obs_norm)
        self.opt_policy = torch.optim.Adam(self.policy.parameters(), lr=cfg.lr)
        self.opt_critic = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr)
        self.estimator = get_estimator(cfg.estimator)
        self.recipient_of = torch.from_numpy(slot_table(layout.recipients.T))  # (n, R): j's recipients, -1 pad
        self.not_recipient = torch.from_numpy(~layout.recipients)  # (n, n): [j, k] k's action may be given
        self.learns_action = torch.from_numpy(~layout.fixed)  # (n,)
        self.codebook = None  # no auxiliary code book here: the run folder's helpers save what a Learner saves
        self.helper: ThreadPoolExecutor | None = None  # where the critic steps run (bitcomm.learn.beside)

    # ---------------------------------------------------------------- critic
    def _queries(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Viewpoints `(q,)` and given actions `(q, n)`: n action baselines (agent j, all others given), then
        (improved) n * R message baselines, rank-major (sender j's k-th recipient, j's recipients masked)."""
        n = self.n
        viewpoint, given = [torch.arange(n)], [~torch.eye(n, dtype=torch.bool)]
        if not self.critic.with_message:
            for k in range(self.recipient_of.shape[1]):
                viewpoint.append(self.recipient_of[:, k].clamp(min=0))
                given.append(self.not_recipient)
        return torch.cat(viewpoint), torch.cat(given)

    def critic_values(self, ro: EnvRollout, it: torch.Tensor, ib: torch.Tensor) -> torch.Tensor:
        """`(M, q)` values of every query at the steps `(it, ib)`; absent agents' actions are never given."""
        viewpoint, given = self._queries()
        M, q = it.shape[0], viewpoint.shape[0]
        rep = torch.arange(M).repeat_interleave(q)
        vp = viewpoint.repeat(M)
        alive = ro.alive[it, ib][rep]
        received = ro.received[it, ib][rep, vp] if self.critic.with_message else None
        v = self.critic(ro.state[it, ib], vp, ro.actions[it, ib][rep], given.repeat(M, 1) & alive, received)
        return v.view(M, q)

    @torch.no_grad()
    def baselines(self, ro: EnvRollout) -> tuple[torch.Tensor, torch.Tensor]:
        """`(T, B, n)` action baselines and `(R, T, B, n)` message baselines (improved; empty for standard)."""
        T, B = ro.valid.shape
        it, ib = ro.valid.nonzero(as_tuple=True)
        values = torch.zeros(T, B, self._queries()[0].shape[0])
        values[it, ib] = self.critic_values(ro, it, ib)
        b_action = values[..., : self.n]
        b_message = values[..., self.n :].reshape(T, B, -1, self.n).permute(2, 0, 1, 3)
        return b_action, b_message

    # ---------------------------------------------------------------- advantages
    def advantages(self, ro: EnvRollout) -> Advantages:
        """The estimator's advantages (multi-recipient for `improved`), zero for absent agents and for the
        actions of fixed agents, and divided by their standard deviation with `adv_norm`."""
        cfg, d = self.cfg, self.layout.delay
        b_action, b_message = self.baselines(ro)
        base = EstimatorBatch(ro.rewards, ro.done, ro.valid, b_action, b_action, ro.dropped)
        if cfg.estimator == "standard":
            adv = self.estimator(base, cfg.gamma, d)
        else:
            present_later = torch.zeros_like(ro.alive)  # [t, b, x]: agent x is present at t + d
            present_later[:-d] = ro.alive[d:]
            action, message, returns = None, torch.zeros_like(b_action), None
            for k in range(self.recipient_of.shape[1]):
                r = self.recipient_of[:, k]
                heard = present_later[:, :, r.clamp(min=0)] & (r >= 0)
                part = self.estimator(
                    base._replace(baseline_message=b_message[k], dropped=ro.dropped | ~heard), cfg.gamma, d
                )
                action, returns = part.action, part.returns
                message = message + part.message
            assert action is not None and returns is not None
            adv = Advantages(action, message, returns)
        mask_a, mask_m = self._masks(ro.alive)
        adv = adv._replace(action=torch.where(mask_a, adv.action, 0.0), message=torch.where(mask_m, adv.message, 0.0))
        if cfg.adv_norm:
            adv = adv._replace(action=scaled(adv.action, mask_a), message=scaled(adv.message, mask_m))
        return adv

    def _masks(self, alive: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Where an action log-probability counts (present, not fixed) and where a message's does (present)."""
        return alive & self.learns_action, alive

    # ---------------------------------------------------------------- update
    def policy_loss(self, ro: EnvRollout, adv: Advantages, cols: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        """The policy's objective on the episodes in columns `cols`: policy gradient + entropy terms only."""
        cfg, policy = self.cfg, self.policy
        valid = ro.valid[:, cols]
        it, ib = valid.nonzero(as_tuple=True)
        bc = cols[ib]
        act_out, msg_logits = policy(ro.obs[it, bc], ro.received[it, bc])
        dist = policy.actions
        mask_a, mask_m = self._masks(ro.alive[it, bc])
        lp_a = torch.where(mask_a, dist.log_prob(act_out, ro.actions[it, bc]), 0.0)
        msg_log_prob, msg_entropy = policy.head.log_prob_and_entropy(msg_logits, ro.bits[it, bc])  # one pass
        lp_m = torch.where(mask_m, msg_log_prob, 0.0)

        def full(x: torch.Tensor) -> torch.Tensor:  # (M, n) -> (T, Bc, n), zero off the valid steps
            out = torch.zeros(*valid.shape, self.n, dtype=x.dtype)
            out[it, ib] = x
            return out

        sub = Advantages(adv.action[:, cols], adv.message[:, cols], adv.returns[:, cols])
        logp_a, logp_m = full(lp_a), full(lp_m)
        if cfg.clip > 0:
            old_a = full(torch.where(mask_a, ro.logp_action[it, bc], 0.0))
            old_m = full(torch.where(mask_m, ro.logp_message[it, bc], 0.0))
            pg = clipped_policy_loss(logp_a, logp_m, old_a, old_m, sub, valid, cfg.clip)
        else:
            pg = policy_gradient_loss(logp_a, logp_m, sub, valid)
        # entropy bonuses, -n w mean H over the agent-steps where each head acts (as objectives.Entropy)
        h_a = _masked_mean(dist.entropy(act_out), mask_a)
        h_m = _masked_mean(msg_entropy, mask_m)
        loss = pg - self.n * (cfg.entropy_action * h_a + cfg.entropy_message * h_m)
        stats = {"losses/policy": pg.item(), "charts/entropy_action": h_a.item(), "charts/entropy_message": h_m.item()}
        if cfg.entropy_message_marginal > 0:  # over the messages sent (objectives.MarginalMessageEntropy)
            h_marginal = marginal_entropy(policy.head, msg_logits[mask_m])
            loss = loss - self.n * cfg.entropy_message_marginal * h_marginal
            stats["charts/entropy_message_marginal"] = h_marginal.item()
        return loss, stats

    def _critic_step(self, ro: EnvRollout, adv: Advantages, cols: torch.Tensor) -> float:
        """One gradient step of the critic on the columns `cols`: regress on Q_t (beside the policy's step where
        a helper thread is given, bitcomm.learn.beside)."""
        it, ib = ro.valid[:, cols].nonzero(as_tuple=True)
        v_loss = critic_mse(self.critic_values(ro, it, cols[ib]), adv.returns[it, cols[ib]])
        _step(self.opt_critic, self.critic, v_loss, self.cfg.max_grad_norm)
        return v_loss.item()

    def update(self, ro: EnvRollout, generator: torch.Generator | None = None) -> dict[str, float]:
        cfg = self.cfg
        adv = self.advantages(ro)
        B = ro.valid.shape[1]
        stats: dict[str, list[float]] = {}
        for cols, with_critic in minibatch_steps(B, cfg.epochs, cfg.minibatches, cfg.critic_epochs, generator):
            critic_step = functools.partial(self._critic_step, ro, adv, cols)
            critic_loss = start(self.helper, critic_step) if with_critic else None  # beside the policy's step
            loss, step_stats = self.policy_loss(ro, adv, cols)
            _step(self.opt_policy, self.policy, loss, cfg.max_grad_norm)
            if critic_loss is not None:
                step_stats["losses/value"] = critic_loss()
            for k, v in step_stats.items():
                stats.setdefault(k, []).append(v)
        return {k: float(np.mean(v)) for k, v in stats.items()}


def _step(opt: torch.optim.Optimizer, net: torch.nn.Module, loss: torch.Tensor, max_norm: float) -> None:
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), max_norm)
    opt.step()


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return torch.where(mask, x, 0.0).sum() / mask.sum().clamp(min=1)
