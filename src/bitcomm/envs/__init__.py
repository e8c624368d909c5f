"""Tasks: the vectorized goal-exchange core (`core.py`, array in, array out over a batch of episodes),
its vectorized view with the channel attached (`vec.py`), the PettingZoo `ParallelEnv`
(`goal_exchange_v0.py`) and text rendering. The grid is one task: it provides the per-agent arrays
the learning core speaks (see `bitcomm.learn.rollout.Rollout`).
`channel_wrapper.BitChannel` puts the same channel on any other PettingZoo `ParallelEnv` (SPEC 8);
`vector.VecEnv` steps B copies of one as arrays (`subproc_vector.SubprocVecEnv`: the same, in worker processes,
for slow envs), and `factory` builds one from `"package.module:factory"`.

May import: `bitcomm.config`, `bitcomm.errors`, `bitcomm.channel`. (`Channel` and the bit conversions
are re-exported here, and `bitcomm.envs.channel` still names them, for code written before the channel
had a package of its own.)
"""

from typing import Any

from bitcomm.channel.core import Channel, bits_to_index, bits_to_onehot, index_to_bits, index_to_onehot
from bitcomm.envs.core import MOVE_NAMES, N_MOVES, FinishedEpisodes, GoalExchangeCore, StepResult
from bitcomm.envs.vec import Observation, VecGoalExchange

__all__ = [
    "MOVE_NAMES",
    "N_MOVES",
    "Channel",
    "FinishedEpisodes",
    "GoalExchangeCore",
    "Observation",
    "StepResult",
    "VecGoalExchange",
    "bits_to_index",
    "bits_to_onehot",
    "goal_exchange_v0",
    "index_to_bits",
    "index_to_onehot",
]


def __getattr__(name: str) -> Any:
    """`goal_exchange_v0` loads on first use: it imports PettingZoo and Gymnasium (0.14 s), which the array core
    and the command line's parsers do not need."""
    if name == "goal_exchange_v0":
        import importlib

        return importlib.import_module("bitcomm.envs.goal_exchange_v0")
    raise AttributeError(f"module 'bitcomm.envs' has no attribute {name!r}")
