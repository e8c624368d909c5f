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

from bitcomm.learn.config import TrainConfig
from bitcomm.learn.level_watch import LevelWatch


class MoveDecay(LevelWatch):
    """The scale of the move regularisers as the schedule is played (1 whole, 0 gone); its watch's `start` is
    where the decay starts."""

    @classmethod
    def from_config(cls, cfg: TrainConfig) -> MoveDecay:
        """The decay `cfg` asks for; with `move_decay_below` the oracle's level on the task is measured once."""
        return cls.at_multiple(cfg.move_decay_below, cfg, "move-decay-below")

    def scale(self, progress: float) -> float:
        """The move regularisers' weight at `progress`: 1 until the start, then linear to 0 at progress 1."""
        if self.start is None:
            return 1.0
        if self.start >= 1.0:
            return 0.0
        return max(0.0, 1.0 - (progress - self.start) / (1.0 - self.start))
