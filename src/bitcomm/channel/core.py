"""The K-bit message channel of SPEC section 2, over a batch of episodes.

A message sent at step t is received at step t + delay. In transit each message is dropped
(all recipients read zeros) with `drop_prob`, and each of its bits flips with `flip_prob`.
Noise has its own seeded random stream, so changing the channel never changes the task's draws.
The channel reports which messages it dropped: the improved estimator gives them no credit.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from bitcomm.config import ChannelConfig, TaskConfig

if TYPE_CHECKING:
    import torch
    from typing_extensions import TypeIs

ArrayT = TypeVar("ArrayT", np.ndarray, "torch.Tensor")


def _is_tensor(x: Any) -> TypeIs[torch.Tensor]:
    """A torch tensor? Torch is not imported here: the environment and the CLI run without it,
    and an object can only be a tensor once its caller has imported torch."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _powers(bits: int, like: ArrayT) -> ArrayT:
    """Place values of the K bits, most significant first."""
    p = [1 << (bits - 1 - k) for k in range(bits)]
    if _is_tensor(like):
        import torch

        return torch.tensor(p, dtype=torch.int64, device=like.device)  # type: ignore[return-value]
    return np.asarray(p, dtype=np.int64)  # type: ignore[return-value]


def bits_to_index(bits: ArrayT) -> ArrayT:
    """`(..., K)` bits in {0, 1} -> `(...)` message index, bit 0 most significant."""
    powers = _powers(bits.shape[-1], bits)
    if _is_tensor(bits):
        return (bits.long() * powers).sum(-1)  # type: ignore[return-value]
    return (bits.astype(np.int64) * powers).sum(-1)  # type: ignore[return-value]


def index_to_bits(index: ArrayT, bits: int) -> ArrayT:
    """`(...)` message index -> `(..., K)` bits, the inverse of `bits_to_index`."""
    powers = _powers(bits, index)
    if _is_tensor(index):
        import torch

        return ((index.long()[..., None] // powers) % 2).to(torch.uint8)  # type: ignore[return-value]
    return ((np.asarray(index, dtype=np.int64)[..., None] // powers) % 2).astype(np.uint8)  # type: ignore[return-value]


def index_to_onehot(index: ArrayT, bits: int) -> ArrayT:
    """`(...)` message index -> `(..., 2^K)` one-hot float vector."""
    if _is_tensor(index):
        import torch

        return torch.nn.functional.one_hot(index.long(), 1 << bits).float()  # type: ignore[return-value]
    return np.eye(1 << bits, dtype=np.float32)[np.asarray(index, dtype=np.int64)]  # type: ignore[return-value]


def bits_to_onehot(bits: ArrayT) -> ArrayT:
    """`(..., K)` bits -> `(..., 2^K)` one-hot: how a one-hot receiver reads the channel."""
    return index_to_onehot(bits_to_index(bits), bits.shape[-1])


class Channel:
    """Delay queue, drops and flips for B independent episodes of n agents."""

    def __init__(
        self,
        config: ChannelConfig,
        slot_senders: np.ndarray,
        num_envs: int,
        seed: int | np.random.SeedSequence | None = None,
    ) -> None:
        """`slot_senders (n, slots)`: the sender heard in each input slot of each agent, -1 for none
        (`bitcomm.config.slot_table`); `config.recipients` is not read, the table says who hears whom."""
        self.config = config
        self.num_envs = num_envs
        self.bits, self.delay = config.bits, config.delay
        self.flip_prob, self.drop_prob = config.flip_prob, config.drop_prob
        n = slot_senders.shape[0]
        self.slot_senders = np.asarray(slot_senders, dtype=np.int64)
        self._slot_mask = (self.slot_senders >= 0)[None, :, :, None]  # (1, n, slots, 1)
        self._slot_index = np.maximum(self.slot_senders, 0)
        # queue[k] holds what was sent k steps ago, after noise; a ring indexed by the clock
        self._queue = np.zeros((self.delay, num_envs, n, self.bits), dtype=np.uint8)
        self._clock = 0
        self.rng = np.random.default_rng(seed)

    @classmethod
    def for_task(cls, task: TaskConfig, num_envs: int, seed: int | np.random.SeedSequence | None = None) -> Channel:
        """The grid task's channel: its config, and who hears whom from its recipients."""
        return cls(task.channel, task.slot_senders, num_envs, seed)

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Forget messages in flight for the episodes in `mask` (all when None)."""
        if mask is None:
            self._queue[:] = 0
        else:
            self._queue[:, mask] = 0

    def transmit(self, sent: np.ndarray) -> np.ndarray:
        """Send `(B, n, K)` bits and advance the clock one step; return `(B, n)` dropped flags.

        What arrives at the next step is then read with `received()`.
        """
        out = sent.astype(np.uint8, copy=True)
        if self.flip_prob > 0.0:
            out ^= (self.rng.random(out.shape) < self.flip_prob).astype(np.uint8)
        if self.drop_prob > 0.0:
            dropped = self.rng.random(out.shape[:2]) < self.drop_prob
            out[dropped] = 0
        else:
            dropped = np.zeros(out.shape[:2], dtype=bool)
        self._queue[self._clock % self.delay] = out
        self._clock += 1
        return dropped

    def received(self) -> np.ndarray:
        """`(B, n, slots, K)`: the messages that arrive at the current step (zeros before any)."""
        arriving = self._queue[self._clock % self.delay]  # sent `delay` steps before the next step
        return np.where(self._slot_mask, arriving[:, self._slot_index], 0).astype(np.uint8)
