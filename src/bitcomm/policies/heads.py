"""Message heads: how a policy parameterizes the K-bit message it sends (paper III-A).

Both heads send K bits over the channel, so they are comparable; they differ in what the network
outputs and in how a receiver reads the bits (SPEC section 2):

- `bitwise`: K independent Bernoulli bits, K outputs; the receiver reads K floats in {0, 1}.
- `onehot`: one categorical over all 2^K messages, 2^K outputs; the receiver reads a one-hot 2^K vector.

A new head touches this file only: the policy never asks which head it has.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from bitcomm.channel.core import bits_to_index, index_to_bits
from bitcomm.errors import bad_value

MAX_MARGINAL_BITS = 12
"""`marginal_entropy` sums over all 2^K messages: at most 4,096 of them."""

SMALLEST_LOG_PROB = -80.0
"""Where `probabilities` floors a log-probability: e^-80 = 1.8e-35, still a normal float32 (float32's exp is
below its smallest normal, 1.2e-38, from -87.3 on)."""


def probabilities(log_probs: torch.Tensor) -> torch.Tensor:
    """`exp(log_probs)` with each log-probability floored at `SMALLEST_LOG_PROB`. On a CPU, torch's exp of an
    input below -87.3 leaves its vectorised path and costs 100-200x more per element; late in training many of a
    near-deterministic head's 2^K message log-probabilities are below -87 (docs/tuning.md, session 32). Below
    e^-80 a probability changes no sum it enters, and its gradient (as small) is dropped."""
    return log_probs.clamp(min=SMALLEST_LOG_PROB).exp()


def marginal_entropy(head: Any, logits: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """H(mean_i Pm(. | s_i)): the entropy of the average message distribution of the rows of `logits (N, out)`,
    exact over all 2^K messages (K <= MAX_MARGINAL_BITS), differentiable. It is largest when different
    senders' states put their mass on different messages; a message two states share lowers it. `weights (N,)`,
    summing to 1: a weighted average (each distinct row weighted by its share of the steps)."""
    return entropy_of(head.mean_probabilities(logits, weights))


def entropy_of(p: torch.Tensor) -> torch.Tensor:
    """The entropy of each distribution `p (..., C)` over its last axis, a probability of 0 counting 0."""
    return -(p * p.clamp(min=1e-30).log()).sum(-1)


def pair_divergence(head: Any, logits: torch.Tensor, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """`(P,)` Jensen-Shannon divergence between the message distributions of rows `first (P,)` and `second (P,)` of
    `logits (N, out)`: H(mixture of the two) - their mean entropy, exact over all 2^K messages (K <=
    MAX_MARGINAL_BITS), differentiable. log 2 when the two put their mass on different messages, 0 when they are the
    same distribution; unlike each entropy it does not ask either to be sharper once they are apart."""
    p = probabilities(head.log_prob_of_terms(head.log_prob_terms(logits)))  # (N, 2^K)
    h = head.entropy(logits)
    return entropy_of((p[first] + p[second]) / 2) - (h[first] + h[second]) / 2


def row_weights(rows: torch.Tensor, count: int) -> torch.Tensor:
    """`(N,)` indices into `count` distinct rows -> `(count,)` each distinct row's share of the N."""
    return torch.bincount(rows, minlength=count).float() / rows.shape[0]


def _weighted_mean(x: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """The mean of the rows of `x (N, C)`, or their average weighted by `weights (N,)`."""
    return x.mean(0) if weights is None else weights.to(x.dtype) @ x


class _MeanProbability(torch.autograd.Function):
    """`(N, C)` log-probabilities -> `(C,)` mean of `probabilities(log_probs)` over the rows (weighted by `(N,)`
    weights where given), with the gradient in closed form, `p * g / N`: autograd's graph of the floor, the
    exponential and the mean writes three more `(N, C)` tensors in the backward pass (the mean's division, the floor's
    mask and its `where`), at K = 10 three `(N, 1024)` ones. Below the floor the gradient is `e^-80 g / N` rather
    than 0: as negligible as the probability itself."""

    @staticmethod
    def forward(ctx: Any, log_probs: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:  # type: ignore[override]
        p = probabilities(log_probs)
        ctx.save_for_backward(p, weights)
        return _weighted_mean(p, weights)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:  # type: ignore[override]
        p, weights = ctx.saved_tensors
        if weights is None:
            return p * (grad / p.shape[0]), None
        return p * grad * weights.to(p.dtype)[:, None], None


def check_marginal_bits(weight: float, bits: int, flag: str = "entropy-message-marginal") -> None:
    """One error line for a bonus that sums over all 2^K messages (`entropy_message_marginal`,
    `message_divergence`) on more than 2^12 of them."""
    if weight > 0 and bits > MAX_MARGINAL_BITS:
        raise bad_value(
            flag,
            weight,
            f"sums over all 2^K messages, so it needs K <= {MAX_MARGINAL_BITS} bits (K = {bits}); leave it at 0",
        )


class BitwiseHead:
    """K independent Bernoulli bits: log P(m) = sum_k log P(bit_k)."""

    name = "bitwise"

    def __init__(self, bits: int) -> None:
        self.bits = bits
        self.out_features = bits  # one logit per bit
        self.in_features = bits  # a receiver reads the bits themselves
        self._which_terms: dict[tuple[int, torch.dtype], torch.Tensor] = {}

    def encode(self, bits: torch.Tensor) -> torch.Tensor:
        return bits.float()

    def linear(self, received: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        """`F.linear(encode(received).flatten(1), weight, bias)` for `(N, slots, K)` received bits: a layer
        reading them."""
        return F.linear(received.flatten(1).to(weight.dtype), weight, bias)

    def log_prob(self, logits: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
        return -F.binary_cross_entropy_with_logits(logits, bits.to(logits.dtype), reduction="none").sum(-1)

    def log_prob_terms(self, logits: torch.Tensor) -> torch.Tensor:
        """`(N, K)` logits -> `(N, 2K)` log P(bit = 1) and log P(bit = 0): every message's log-probability
        is linear in them, so their mean over samples gives every message's mean log-probability."""
        return F.logsigmoid(torch.cat([logits, -logits], -1))

    def log_prob_of_terms(self, terms: torch.Tensor) -> torch.Tensor:
        """`(N, 2K)` terms (or their means) -> `(N, 2^K)` log-probability of every message (by index): one product
        with the `(2K, 2^K)` matrix of which term each message sums (built once per size and dtype)."""
        bits = terms.shape[-1] // 2
        key = (bits, terms.dtype)
        if key not in self._which_terms:
            codes = index_to_bits(torch.arange(1 << bits), bits).to(terms.dtype)  # (2^k, k)
            self._which_terms[key] = torch.cat([codes.T, 1 - codes.T])
        return terms @ self._which_terms[key]

    def mean_probabilities(self, logits: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
        """`(N, K)` logits -> `(2^K,)` mean over the rows of every message's probability (by index; weighted by
        `weights (N,)`, summing to 1, where given). A message's
        probability is the product of its first K // 2 bits' and its last bits' probabilities, so the mean is one
        `(2^(K//2), N) x (N, 2^(K - K//2))` product: at K = 7 it writes `(N, 8 + 16)` probabilities where the
        every-message table writes `(N, 128)`, at K = 10 64 against 1,024 (that table was a third of a 32x32
        update: docs/tuning.md, session 33). Each half's log-probability is floored as in `probabilities`, so a
        message below e^-160 counts as 0."""
        first = self.bits // 2
        if first == 0:  # K = 1: one half
            return _weighted_mean(probabilities(self.log_prob_of_terms(self.log_prob_terms(logits))), weights)
        parts = logits.split([first, self.bits - first], -1)
        a, b = (probabilities(self.log_prob_of_terms(self.log_prob_terms(part))) for part in parts)
        if weights is None:
            return (a.T @ b).flatten() / logits.shape[0]
        return ((a * weights.to(a.dtype)[:, None]).T @ b).flatten()

    def entropy(self, logits: torch.Tensor) -> torch.Tensor:
        p = torch.sigmoid(logits)
        return F.binary_cross_entropy_with_logits(logits, p, reduction="none").sum(-1)

    def log_prob_and_entropy(self, logits: torch.Tensor, bits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`log_prob(logits, bits)` and `entropy(logits)`, what an update needs of every sent message."""
        return self.log_prob(logits, bits), self.entropy(logits)

    def log_prob_and_entropy_of_rows(
        self, logits: torch.Tensor, rows: torch.Tensor, bits: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`log_prob_and_entropy(logits[rows], bits)` for `(U, K)` distinct logits and `(N,)` rows: K terms a row,
        as cheap gathered as not."""
        return self.log_prob_and_entropy(logits[rows], bits)

    def sample(self, logits: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        u = torch.rand(logits.shape, generator=generator, device=logits.device)
        return (u < torch.sigmoid(logits)).to(torch.uint8)

    def mode(self, logits: torch.Tensor) -> torch.Tensor:
        return (logits > 0).to(torch.uint8)

    def straight_through(self, logits: torch.Tensor, received: torch.Tensor, flips: torch.Tensor) -> torch.Tensor:
        """The received encoding, equal in value to `encode(received)`, with the gradient of the
        sender's bit probabilities (sign reversed where the channel flipped the bit)."""
        p = torch.sigmoid(logits)
        sign = 1.0 - 2.0 * flips.float()
        return received.float() + sign * (p - p.detach())

    def relaxed(self, logits: torch.Tensor, flips: torch.Tensor, noise: float) -> torch.Tensor:
        """A differentiable stand-in for the received bits: sigmoid(logit + noise * N(0, 1)), flipped
        where the channel flipped (DIAL's regularised channel). The noise pushes bits to saturate."""
        q = torch.sigmoid(logits + noise * torch.randn_like(logits))
        return torch.where(flips.bool(), 1.0 - q, q)


class OneHotHead:
    """One categorical over the 2^K messages, sent as the K bits of the message index."""

    name = "onehot"

    def __init__(self, bits: int) -> None:
        self.bits = bits
        self.out_features = 1 << bits
        self.in_features = 1 << bits

    def encode(self, bits: torch.Tensor) -> torch.Tensor:
        return F.one_hot(bits_to_index(bits), self.out_features).float()

    def linear(self, received: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        """`F.linear(encode(received).flatten(1), weight, bias)` for `(N, slots, K)` received bits, as the sum of
        the weight's columns of the messages that arrived: at K = 10 the product with a 2^K-wide one-hot and its
        gradient cost about 15x more (docs/tuning.md, session 16)."""
        slot = torch.arange(received.shape[-2], device=received.device) * self.in_features
        out = F.embedding(bits_to_index(received) + slot, weight.T).sum(-2)
        return out if bias is None else out + bias

    def log_prob(self, logits: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
        return torch.log_softmax(logits, -1).gather(-1, bits_to_index(bits)[..., None])[..., 0]

    def log_prob_terms(self, logits: torch.Tensor) -> torch.Tensor:
        """`(N, 2^K)` logits -> the log-probability of every message, which is its own linear term."""
        return torch.log_softmax(logits, -1)

    def log_prob_of_terms(self, terms: torch.Tensor) -> torch.Tensor:
        return terms

    def mean_probabilities(self, logits: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
        """`(N, 2^K)` logits -> `(2^K,)` mean over the rows of every message's probability (weighted by `weights
        (N,)`, summing to 1, where given)."""
        return _MeanProbability.apply(torch.log_softmax(logits, -1), weights)

    def entropy(self, logits: torch.Tensor) -> torch.Tensor:
        logp = torch.log_softmax(logits, -1)
        return -(probabilities(logp) * logp).sum(-1)

    def log_prob_and_entropy(self, logits: torch.Tensor, bits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`log_prob(logits, bits)` and `entropy(logits)` from one log-softmax, with their gradient in closed
        form: over 2^K outputs, autograd's graph of the two (two log-softmaxes, the gather's zero-filled
        gradient, the entropy's products) is most of a one-hot update's time (docs/tuning.md, session 16)."""
        return _LogProbAndEntropy.apply(logits, bits_to_index(bits))

    def log_prob_and_entropy_of_rows(
        self, logits: torch.Tensor, rows: torch.Tensor, bits: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`log_prob_and_entropy(logits[rows], bits)` for `(U, 2^K)` distinct logits and `(N,)` rows, from one
        log-softmax of the U rows: the `(N, 2^K)` tables of every row are what it saves."""
        logp = torch.log_softmax(logits, -1)
        entropy = -(probabilities(logp) * logp).sum(-1)
        return logp[rows, bits_to_index(bits)], entropy[rows]

    def sample(self, logits: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """By the inverse of the cumulative distribution: one uniform number per message, where
        `torch.multinomial` draws one per outcome (at K = 10, 1,024 of them: most of a rollout's time)."""
        cdf = torch.softmax(logits.reshape(-1, self.out_features), -1).cumsum(-1)
        u = torch.rand(cdf.shape[0], 1, generator=generator, device=logits.device) * cdf[:, -1:]
        index = torch.searchsorted(cdf, u, right=True).clamp_(max=self.out_features - 1)
        return index_to_bits(index[:, 0].reshape(logits.shape[:-1]), self.bits)

    def mode(self, logits: torch.Tensor) -> torch.Tensor:
        return index_to_bits(logits.argmax(-1), self.bits)

    def straight_through(self, logits: torch.Tensor, received: torch.Tensor, flips: torch.Tensor) -> torch.Tensor:
        """One-hot of what arrived, with the gradient of the probability of each message that the
        channel's flip pattern would turn into it (message index XOR flip pattern)."""
        p = torch.softmax(logits, -1)
        perm = torch.arange(self.out_features, device=logits.device) ^ bits_to_index(flips)[..., None]
        p_seen = p.gather(-1, perm)
        return self.encode(received) + (p_seen - p_seen.detach())

    def relaxed(self, logits: torch.Tensor, flips: torch.Tensor, noise: float) -> torch.Tensor:
        """softmax(logits + noise * N(0, 1)), permuted by the channel's flip pattern."""
        q = torch.softmax(logits + noise * torch.randn_like(logits), -1)
        perm = torch.arange(self.out_features, device=logits.device) ^ bits_to_index(flips)[..., None]
        return q.gather(-1, perm)


class _LogProbAndEntropy(torch.autograd.Function):
    """`(N, C)` logits and `(N,)` indices -> log p_index and H(p), p = softmax(logits). Gradients:
    d log p_i / d logits = onehot(i) - p, and dH / d logits = -p * (log p + H)."""

    @staticmethod
    def forward(ctx: Any, logits: torch.Tensor, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[override]
        logp = torch.log_softmax(logits, -1)
        p = probabilities(logp)
        entropy = -(p * logp).sum(-1)
        ctx.save_for_backward(logp, p, entropy, index)
        return logp.gather(-1, index[..., None])[..., 0], entropy

    @staticmethod
    def backward(ctx: Any, g_logp: torch.Tensor, g_entropy: torch.Tensor) -> tuple[torch.Tensor, None]:  # type: ignore[override]
        logp, p, entropy, index = ctx.saved_tensors
        grad = (logp + entropy[..., None]).mul_(g_entropy[..., None]).add_(g_logp[..., None]).mul_(p).neg_()
        return grad.scatter_add_(-1, index[..., None], g_logp[..., None]), None


MessageHead = BitwiseHead | OneHotHead
MESSAGE_HEADS: dict[str, type[MessageHead]] = {"bitwise": BitwiseHead, "onehot": OneHotHead}


def make_head(name: str, bits: int) -> MessageHead:
    if name not in MESSAGE_HEADS:
        raise bad_value("messages", name, f"choose one of {', '.join(MESSAGE_HEADS)}")
    return MESSAGE_HEADS[name](bits)
