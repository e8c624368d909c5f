"""Acting with a policy network: one function shared by training rollouts, evaluation and `Controller`,
so that what is trained, measured and deployed cannot drift apart."""

from __future__ import annotations

import numpy as np
import torch

from bitcomm.envs.vec import Observation
from bitcomm.policies.networks import PolicyNet


@torch.no_grad()
def act(
    net: PolicyNet,
    planes: torch.Tensor,
    received: torch.Tensor,
    greedy: bool = False,
    generator: torch.Generator | None = None,
    greedy_messages: torch.Tensor | None = None,
    message_logits: torch.Tensor | None = None,
    held_messages: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moves `(N,)`, bits `(N, K)` and their log-probabilities for `(N, 2, S, S)` planes and `(N, slots, K)` bits.

    Sampling (the default) is how the policy was trained; `greedy` takes the most likely move and message;
    `greedy_messages (N,)` bool, the most likely message of those rows only (their moves sampled);
    `message_logits (N, out)`, the rows' message logits where the caller has them (`PolicyNet.observed_message_logits`,
    once per episode): the network then runs its movement part alone; `held_messages`, `(N,)` bool rows and their
    `(N, K)` bits, words the caller drew from these logits earlier in the episode, which those rows send again.
    """
    if message_logits is None:
        move_logits, message_logits = net(planes, received)
    else:
        move_logits = net.move_logits(net.hidden(planes, received))
    if greedy:
        moves, bits = move_logits.argmax(-1), net.head.mode(message_logits)
    else:
        moves = torch.multinomial(torch.softmax(move_logits, -1), 1, generator=generator)[:, 0]
        bits = net.head.sample(message_logits, generator)
        if greedy_messages is not None:
            bits = torch.where(greedy_messages[:, None], net.head.mode(message_logits), bits)
        if held_messages is not None:
            bits = torch.where(held_messages[0][:, None], held_messages[1], bits)
    logp_move = torch.log_softmax(move_logits, -1).gather(-1, moves[:, None])[:, 0]
    return moves, bits, logp_move, net.head.log_prob(message_logits, bits)


class NetworkPolicy:
    """A policy network as a batched `Policy` (Observation -> moves, bits) for the evaluator."""

    def __init__(self, net: PolicyNet, greedy: bool = False, seed: int | None = None) -> None:
        self.net, self.greedy = net, greedy
        self.generator = torch.Generator().manual_seed(0 if seed is None else seed)

    def __call__(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        B, n = obs.planes.shape[:2]
        planes = torch.from_numpy(obs.planes).flatten(0, 1)
        received = torch.from_numpy(obs.received).flatten(0, 1)
        moves, bits, _, _ = act(self.net, planes, received, self.greedy, self.generator)
        return moves.reshape(B, n).numpy(), bits.reshape(B, n, -1).numpy()
