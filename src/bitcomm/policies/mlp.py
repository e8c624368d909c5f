"""Policy and critic networks for any channel-wrapped env with vector observations (SPEC sections 3 and 8).

The grid's networks (`networks.py`) read planes; these read the arrays of `bitcomm.envs.vector`:

- Policy, shared by every agent: [padded observation, the agent's one-hot id, the received messages as the
  receiver's head reads them (bitwise: K floats per slot; one-hot: 2^K per slot)] -> an MLP trunk -> an
  action head and a message head (`heads.py`). The action head is a categorical over the agent's own
  actions (logits of actions it lacks are masked) for Discrete envs, or a diagonal Gaussian with a
  state-independent log standard deviation for Box envs (the env side clips samples to the bounds).
- Critic (training only): [state, the judged agent's one-hot id, every other agent's action with a "given"
  flag (zeros where not given), and for V1 the messages the judged agent received] -> an MLP -> V. As on
  the grid, one network answers every baseline: mask the actions a query must not see.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from bitcomm.envs.vector import EnvLayout
from bitcomm.policies.heads import MessageHead, make_head, probabilities
from bitcomm.policies.networks import concat_linear


def mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers with tanh between them (and after the last: a trunk, not a head)."""
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:], strict=True):
        layers += [nn.Linear(a, b), nn.Tanh()]
    return nn.Sequential(*layers)


class CategoricalActions:
    """One categorical per agent over its own actions; `mask (n, A)` removes the actions an agent lacks."""

    def __init__(self, mask: torch.Tensor) -> None:
        self.mask = mask

    def log_softmax(self, out: torch.Tensor) -> torch.Tensor:
        """`(N, n, A)` logits -> log-probabilities, about -1e9 where masked (finite, so no NaN gradient)."""
        return torch.log_softmax(out.masked_fill(~self.mask, -1e9), -1)

    def log_prob(self, out: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.log_softmax(out).gather(-1, action[..., None].long())[..., 0]

    def entropy(self, out: torch.Tensor) -> torch.Tensor:
        logp = self.log_softmax(out)
        return -torch.where(self.mask, probabilities(logp) * logp, 0.0).sum(-1)

    def sample(self, out: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        probs = self.log_softmax(out).exp()
        return torch.multinomial(probs.flatten(0, -2), 1, generator=generator).view(probs.shape[:-1])

    def mode(self, out: torch.Tensor) -> torch.Tensor:
        return self.log_softmax(out).argmax(-1)


class GaussianActions:
    """A diagonal Gaussian per agent, mean from the network, log std a parameter; padded dims are ignored."""

    def __init__(self, mask: torch.Tensor, log_std: torch.Tensor) -> None:
        self.mask, self.log_std = mask, log_std

    def log_prob(self, out: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        z = (action - out) * torch.exp(-self.log_std)
        per_dim = -0.5 * z**2 - self.log_std - 0.5 * math.log(2 * math.pi)
        return torch.where(self.mask, per_dim, 0.0).sum(-1)

    def entropy(self, out: torch.Tensor) -> torch.Tensor:
        per_dim = (self.log_std + 0.5 * math.log(2 * math.pi * math.e)).expand_as(out)
        return torch.where(self.mask, per_dim, 0.0).sum(-1)

    def sample(self, out: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        noise = torch.randn(out.shape, generator=generator)
        return torch.where(self.mask, out + noise * torch.exp(self.log_std), 0.0)

    def mode(self, out: torch.Tensor) -> torch.Tensor:
        return torch.where(self.mask, out, 0.0)


ActionDistribution = CategoricalActions | GaussianActions


class RunningNorm(nn.Module):
    """Inputs standardised by a running mean and variance per feature (`shape`), clipped to +-10, as PPO
    implementations do for vector observations. The statistics are buffers (saved with the weights); they
    change only through `update`, which the trainer calls after each learning update, so one batch is acted
    on and learned from under the same statistics. Off (`enabled=False`): the identity."""

    mean: torch.Tensor  # buffers, declared so that type checkers see tensors
    var: torch.Tensor
    count: torch.Tensor

    def __init__(self, shape: tuple[int, ...], enabled: bool) -> None:
        super().__init__()
        self.enabled = enabled
        self.register_buffer("mean", torch.zeros(shape))
        self.register_buffer("var", torch.ones(shape))
        self.register_buffer("count", torch.zeros(shape))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return x
        return ((x - self.mean) / torch.sqrt(self.var + 1e-8)).clamp(-10.0, 10.0)

    @torch.no_grad()
    def update(self, x: torch.Tensor, mask: torch.Tensor) -> None:
        """Fold in the samples `x (..., *shape)` where `mask` (over `x`'s leading dimensions, or more) is true
        (Chan et al.'s parallel update; a feature with no new sample keeps its statistics)."""
        if not self.enabled:
            return
        dims = tuple(range(x.dim() - self.mean.dim()))  # the sample dimensions
        w = mask.to(x.dtype).reshape(*mask.shape, *([1] * (x.dim() - mask.dim())))
        k = w.sum(dims).expand_as(self.count)
        mean = (x * w).sum(dims) / k.clamp(min=1)
        var = (((x - mean) ** 2) * w).sum(dims) / k.clamp(min=1)
        n0, total = self.count, self.count + k
        t = total.clamp(min=1)
        delta = mean - self.mean
        self.var.copy_(torch.where(total > 0, self.var * n0 / t + var * k / t + delta**2 * n0 * k / t**2, self.var))
        self.mean.add_(delta * k / t)
        self.count.copy_(total)


class MlpPolicy(nn.Module):
    """pi(a | o, m_rec, id) and Pm(m | o, m_rec, id) for every agent at once, from one set of parameters."""

    def __init__(self, layout: EnvLayout, messages: str, hidden: tuple[int, ...], obs_norm: bool = False) -> None:
        super().__init__()
        self.layout = layout
        self.obs_norm = RunningNorm((layout.n, layout.obs_dim), obs_norm)
        n, A = layout.n, layout.action_dim
        self.head: MessageHead = make_head(messages, layout.bits)
        self.register_buffer("agent_ids", torch.eye(n), persistent=False)
        self.register_buffer("action_mask", torch.from_numpy(layout.action_mask), persistent=False)
        inputs = layout.obs_dim + n + layout.slots * self.head.in_features
        self.trunk = mlp([inputs, *hidden])
        self.action_out = nn.Linear(hidden[-1], A)
        self.message_out = nn.Linear(hidden[-1], self.head.out_features)
        with torch.no_grad():  # start near uniform (discrete) or near zero mean (Box), as CleanRL's actor head
            self.action_out.weight.mul_(0.01)
            self.action_out.bias.zero_()
        self.log_std = nn.Parameter(torch.zeros(A)) if not layout.discrete else None

    @property
    def actions(self) -> ActionDistribution:
        mask: torch.Tensor = self.action_mask  # type: ignore[assignment]
        if self.log_std is None:
            return CategoricalActions(mask)
        return GaussianActions(mask, self.log_std)

    def forward(self, obs: torch.Tensor, received: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`obs (N, n, D)`, `received (N, n, slots, K)` -> action outputs `(N, n, A)` (logits or means) and
        message logits `(N, n, out)`."""
        N, n = obs.shape[:2]
        ids: torch.Tensor = self.agent_ids  # type: ignore[assignment]
        x = torch.cat([self.obs_norm(obs.float()), ids.expand(N, n, n), self.head.encode(received).flatten(2)], -1)
        h = self.trunk(x)
        return self.action_out(h), self.message_out(h)

    def draw(
        self, act_out: torch.Tensor, msg_logits: torch.Tensor, greedy: bool, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions and message bits from `forward`'s outputs: sampled from `generator`, or with `greedy` the most
        likely of each (the one rule of evaluation's rollout and `bitcomm.EnvController`)."""
        dist = self.actions
        if greedy:
            return dist.mode(act_out), self.head.mode(msg_logits)
        return dist.sample(act_out, generator), self.head.sample(msg_logits, generator)


class MlpCritic(nn.Module):
    """V(state, whose value, others' actions with "given" flags [, the messages that agent received]).

    `with_message=True` is V1 (standard estimator), `False` V2 (improved estimator)."""

    def __init__(
        self, layout: EnvLayout, messages: str, hidden: tuple[int, ...], with_message: bool, obs_norm: bool = False
    ) -> None:
        super().__init__()
        self.layout, self.with_message = layout, with_message
        self.state_norm = RunningNorm((layout.state_size,), obs_norm)
        self.head = make_head(messages, layout.bits)
        n, A = layout.n, layout.action_dim
        extra = layout.slots * self.head.in_features if with_message else 0
        self.body = mlp([layout.state_size + n + n * (A + 1) + extra, *hidden])
        self.out = nn.Linear(hidden[-1], 1)

    def encode_actions(self, actions: torch.Tensor, given: torch.Tensor) -> torch.Tensor:
        """`actions (M, n)` int or `(M, n, A)` float, `given (M, n)` -> `(M, n * (A + 1))`."""
        g = given.float()[..., None]
        if self.layout.discrete:
            a = nn.functional.one_hot(actions.long(), self.layout.action_dim).float()
        else:
            a = actions.float()
        return torch.cat([a * g, g], -1).flatten(1)

    def forward(
        self,
        state: torch.Tensor,
        viewpoint: torch.Tensor,
        actions: torch.Tensor,
        given: torch.Tensor,
        received: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """`state (S, Ds)`, `viewpoint (N,)`, `actions (N, n[, A])`, `given (N, n)`, `received (N, slots, K)` ->
        `(N,)`, for N queries about S states, each state's N // S queries consecutive: the state's share of the
        first layer is computed once per state (`concat_linear`)."""
        parts = [nn.functional.one_hot(viewpoint, self.layout.n).float(), self.encode_actions(actions, given)]
        if self.with_message:
            assert received is not None, "V1 conditions on the received messages"
            parts.append(self.head.encode(received).flatten(1))
        h = concat_linear(self.body[0], self.state_norm(state.float()), torch.cat(parts, -1))
        return self.out(self.body[1:](h))[:, 0]
