"""Where in the schedule the protocol formed: the first update at which the rolling training episode length was at
most a multiple of the oracle's.

A schedule that starts at a fixed fraction of the budget starts at a different stage of learning on every task:
the protocol of the paper's 10x10 task forms in the budget's first quarter, a 32x32 one late or not at all. Two
schedules wait for the protocol instead: the move regularisers' decay (`TrainConfig.move_decay_below`,
`bitcomm.learn.move_decay`) and the senders' other ways of sending (`TrainConfig.senders_wait_below`: the greedy
senders and held words). A watch latches: a relapse later does not undo it, and a checkpoint carries where it
started, so a resumed run continues the same schedule.
"""

from __future__ import annotations

from typing import TypeVar

from bitcomm.errors import bad_value
from bitcomm.learn.config import TrainConfig

W = TypeVar("W", bound="LevelWatch")


class LevelWatch:
    """The schedule's progress at which the rolling episode length first reached `threshold` (None: not yet)."""

    def __init__(self, threshold: float | None) -> None:
        self.threshold = threshold
        """The rolling episode length at or below which the watch starts (None: it started with the first episode)."""
        self.start: float | None = 0.0 if threshold is None else None
        """The schedule's progress (`TrainConfig.schedule_progress`) where it started; None: not yet."""

    @classmethod
    def at_multiple(cls: type[W], multiple: float, cfg: TrainConfig, flag: str) -> W:
        """A watch for `multiple` times the oracle's episode length on `cfg`'s task (0: started from the first
        episode), measured once per task and seed on episodes cut as training's are: the rolling length it is
        compared with counts a cut episode's steps up to the cut. (Against the oracle's full-length mean, 1.15x the
        oracle on 32x32 asked for 31.5 steps out of 32, 1.24x the oracle over the same cut episodes; from about
        40x40 it passed 32, so every cut rolling length met it.) Where even the cut oracle's multiple is at least the
        length training cuts at, no rolling length can tell the protocol apart, and the first one meets it."""
        if multiple == 0:
            return cls(None)
        from bitcomm.learn.run_folder import training_oracle_level

        oracle = training_oracle_level(cfg)
        if oracle is None:
            raise bad_value(flag, multiple, "needs the oracle, which cannot play this task")
        return cls(multiple * oracle)

    @property
    def waits(self) -> bool:
        """Whether this watch waits for a level (a checkpoint then records where it started)."""
        return self.threshold is not None

    def watch(self, rolling_length: float | None, progress: float) -> None:
        """Start at `progress` if not started and the rolling length has reached the threshold."""
        if self.start is not None or self.threshold is None or rolling_length is None:
            return
        if rolling_length <= self.threshold:
            self.start = progress


PROTOCOL_FORMED = "schedule/protocol_formed"
"""The metrics column that says whether the greedy senders and held words may play (`senders_wait_below`)."""


class SendersWait(LevelWatch):
    """When the greedy senders and held words may start (`TrainConfig.senders_wait_below`): at the later of their
    own `_from` and the progress where the protocol formed."""

    @classmethod
    def from_config(cls, cfg: TrainConfig) -> SendersWait:
        return cls.at_multiple(cfg.senders_wait_below, cfg, "senders-wait-below")

    def figures(self) -> dict[str, float]:
        """The log's `PROTOCOL_FORMED` column where the watch waits: 1 from the update that saw the protocol formed."""
        return {PROTOCOL_FORMED: float(self.start is not None)} if self.waits else {}
