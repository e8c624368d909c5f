"""When the move regularisers' decay starts (`TrainConfig.move_decay_below`).

The default decays the move entropy bonus and the uniform-move pull over the whole budget, so that greedy
moves end as good as sampled ones. Where the budget is long against the time the protocol takes to form
(32x32, docs/tuning.md session 22), that decay bites while the senders are still finding their codes and
slows the second half of learning. Started from the protocol's progress instead (the rolling training
episode length at most a multiple of the oracle's), the regularisers stay whole until the agents can play,
then decay linearly to zero by the schedule's end, where the learning rates reach zero too. Measured
(docs/tuning.md session 23): at 32x32 it ends level with no decay at all; at 10x10 it is behind the decay from
the first episode, which stays the default.
"""

from __future__ import annotations

from bitcomm.errors import bad_value
from bitcomm.learn.config import TrainConfig


class MoveDecay:
    """The scale of the move regularisers as the schedule is played (1 whole, 0 gone)."""

    def __init__(self, threshold: float | None) -> None:
        self.threshold = threshold
        """The rolling episode length at or below which the decay starts (None: from the first episode)."""
        self.start: float | None = 0.0 if threshold is None else None
        """The schedule's progress (`TrainConfig.schedule_progress`) where the decay started; None: not yet."""

    @classmethod
    def from_config(cls, cfg: TrainConfig) -> MoveDecay:
        """The decay `cfg` asks for; with `move_decay_below` the oracle's level on the task is measured once."""
        if cfg.move_decay_below == 0:
            return cls(None)
        from bitcomm.learn.run_folder import oracle_level

        oracle = oracle_level(cfg)
        if oracle is None:
            raise bad_value("move-decay-below", cfg.move_decay_below, "needs the oracle, which cannot play this task")
        return cls(cfg.move_decay_below * oracle)

    def watch(self, rolling_length: float | None, progress: float) -> None:
        """Start the decay at `progress` if it has not started and the rolling length has reached the threshold."""
        if self.start is not None or self.threshold is None or rolling_length is None:
            return
        if rolling_length <= self.threshold:
            self.start = progress

    def scale(self, progress: float) -> float:
        """The move regularisers' weight at `progress`: 1 until the start, then linear to 0 at progress 1."""
        if self.start is None:
            return 1.0
        if self.start >= 1.0:
            return 0.0
        return max(0.0, 1.0 - (progress - self.start) / (1.0 - self.start))
