"""Self-labelled message codes (option `TrainConfig.code_coef`): which message tells which goal.

A sender is trained toward one code word per goal it observes. The words are not fixed in advance:
every update matches the goals seen so far to messages by the sender's own running preference (each
message's mean log-probability when the sender last saw that goal), one goal per message, most
confident goal first, so the sender keeps what it already says and two goals never share a word.
That matching is what a relaxed channel never found (two goals sharing a code stay stuck together;
docs/tuning.md), in the spirit of self-labelling with an equipartition constraint (Asano et al.
2020). It uses only the goal the sender observes, never privileged state. With fewer messages than
cells (2^bits < size^2) goals share messages as evenly as the matching allows.

The book is a module of buffers so that checkpoints carry it and A3C workers can share it in memory.
"""

from __future__ import annotations

import torch
from torch import nn

from bitcomm.channel.core import index_to_bits
from bitcomm.policies.heads import MessageHead


def greedy_matching(scores: torch.Tensor) -> torch.Tensor:
    """`(G, C)` scores -> `(G,)` columns: rows in order of their best score, each taking its best column
    not yet full. A column holds one row when G <= C, else at most ceil(G / C) (no code without sharing)."""
    scores = scores.clone()
    cap = -(-scores.shape[0] // scores.shape[1])
    uses = [0] * scores.shape[1]
    word = torch.empty(scores.shape[0], dtype=torch.long)
    for row in scores.max(1).values.argsort(descending=True).tolist():
        col = int(scores[row].argmax())
        word[row] = col
        uses[col] += 1
        if uses[col] == cap:
            scores[:, col] = -torch.inf
    return word


class CodeBook(nn.Module):
    preference: torch.Tensor
    seen: torch.Tensor

    def __init__(self, n_goals: int, head: MessageHead) -> None:
        super().__init__()
        self.head = head
        terms = head.log_prob_terms(torch.zeros(1, head.out_features)).shape[1]
        self.register_buffer("preference", torch.zeros(n_goals, terms))
        self.register_buffer("seen", torch.zeros(n_goals, dtype=torch.bool))

    @torch.no_grad()
    def targets(self, goals: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """`goals (N,)` observed by senders whose message logits are `(N, out)` -> `(N, K)` target bits."""
        present, inverse = torch.unique(goals, return_inverse=True)
        counts = torch.bincount(inverse, minlength=len(present)).to(logits.dtype)[:, None]
        terms = self.head.log_prob_terms(logits.detach())
        self.preference[present] = torch.zeros(len(present), terms.shape[1]).index_add_(0, inverse, terms) / counts
        self.seen[present] = True
        known = self.seen.nonzero()[:, 0]
        word = torch.full((self.seen.shape[0],), -1, dtype=torch.long)
        word[known] = greedy_matching(self.head.log_prob_of_terms(self.preference[known]))
        return index_to_bits(word[goals], self.head.bits)
