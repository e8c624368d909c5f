"""Flush denormal floats to zero while training and evaluating: the same numbers, without the CPU's slow path.

Late in training the policy is nearly deterministic: its logits reach tens, so sigmoids, softmaxes, their
logarithms and the gradients through them produce numbers below float32's smallest normal (1.2e-38). An x86
CPU computes with such denormals in microcode, many times slower per operation. `flush_denormals` turns on the
CPU's flush-to-zero and denormals-are-zero modes (`torch.set_flush_denormal`) for the thread that trains or
evaluates (`bitcomm.policies.evaluation.evaluate`, so `bitcomm eval` measures what a run's checks measured) and
puts the previous mode back after: every number below 1.2e-38 reads as 0, far below anything a loss, an
advantage or a gradient step can resolve. It makes a trained 32x32 one-hot run's update 1.4x quicker
(`benchmarks/denormals.py`, docs/tuning.md session 32); a CPU without the modes (ARM) runs as before.

The mode belongs to a thread: the critic's helper thread takes the trainer's (`bitcomm.learn.beside`), so a run
on two threads stays the run on one bit for bit. Set `BITCOMM_FLUSH_DENORMALS=0` to leave the CPU's mode alone."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch

ENV_VAR = "BITCOMM_FLUSH_DENORMALS"


def denormals_flushed() -> bool:
    """Whether this thread flushes denormals (torch has no getter: with the modes on, a denormal times one is 0)."""
    return bool((torch.full((1,), 1e-39) * 1.0).item() == 0.0)


@contextlib.contextmanager
def flush_denormals() -> Iterator[None]:
    """Flush denormals in this thread while training or evaluating, unless `BITCOMM_FLUSH_DENORMALS=0`; the
    previous mode is restored on exit."""
    if os.environ.get(ENV_VAR, "1") == "0":
        yield
        return
    previous = denormals_flushed()
    torch.set_flush_denormal(True)  # a no-op on a CPU without the modes
    try:
        yield
    finally:
        torch.set_flush_denormal(previous)
