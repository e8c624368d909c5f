"""The precision of an update's network passes (`TrainConfig.update_dtype`).

`bfloat16` runs the policy's and the critics' passes of each minibatch step under `torch.autocast`: their
matrix products take bfloat16 inputs and accumulate in float32, which on a CPU with native bfloat16
(AVX512-BF16 or AMX) costs about half of float32's; without it, it costs more. What is computed from
those passes (log-probabilities, entropies, the critic's error, gradients' sums) and everything else,
acting included, stays float32: the weights and the optimizer's state are float32 throughout, so a
bfloat16 run's checkpoints are the same kind as any other. docs/tuning.md (session 15) says what it buys.
"""

from __future__ import annotations

import contextlib

import torch

UPDATE_DTYPES = ("float32", "bfloat16")


def update_precision(dtype: str) -> contextlib.AbstractContextManager[object]:
    """The context an update's forward passes run in; autocast state is per thread, so a step on a helper
    thread (bitcomm.learn.beside) enters its own."""
    if dtype == "bfloat16":
        return torch.autocast("cpu", dtype=torch.bfloat16)
    return contextlib.nullcontext()
