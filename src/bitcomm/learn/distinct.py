"""The distinct rows of a batch's inputs, so that a layer reads each distinct input once.

A message head that reads only the goal the sender observes (`message_reads` `observed`) sees at most S^2
different inputs in a batch of thousands of agent-steps (10x10: 100 in 8,192). Its layers run over those rows
and the rows are gathered back: the same values, and gradients summed in another order (equal to rounding).

`torch.unique(dim=0)` sorts whole rows and costs more than the layers it would save, so the rows are grouped by
an integer hash of their bits and every row is then compared with its group's first row: a collision (two
different rows on one hash) fails that check, and only then are the rows sorted whole.
"""

from __future__ import annotations

import torch

_SAME_WIDTH = {1: torch.uint8, 2: torch.int16, 4: torch.int32, 8: torch.int64}
"""An integer dtype of each element width, to read a row's bits by."""


def distinct_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`x (N, w)` -> `(rows (U, w), inverse (N,))` with `rows[inverse]` equal to `x` bit for bit, `U` the number
    of distinct rows (at most N; equal rows always share one)."""
    x = x.contiguous()
    bits = x.view(_SAME_WIDTH[x.element_size()]).to(torch.int64)
    if x.element_size() == 8:  # keep the products below 2^63: the hash reads the low 32 bits and the high ones
        bits = torch.cat([bits & 0xFFFFFFFF, bits >> 32], 1)
    weights = torch.randint(-(2**20), 2**20, (bits.shape[1],), generator=torch.Generator().manual_seed(0))
    keys, inverse = torch.unique((bits * weights).sum(1), return_inverse=True)  # |sum| < w * 2^51
    first = torch.empty(len(keys), dtype=torch.long).scatter_(0, inverse, torch.arange(len(x)))
    rows = x[first]
    if torch.equal(rows[inverse], x):
        return rows, inverse
    return torch.unique(x, dim=0, return_inverse=True)  # a collision (or NaN, never equal to itself)
