"""Environments: the vectorized goal-exchange core, its channel, and the PettingZoo view."""

from bitcomm.envs import goal_exchange_v0
from bitcomm.envs.channel import Channel, bits_to_index, bits_to_onehot, index_to_bits, index_to_onehot
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
