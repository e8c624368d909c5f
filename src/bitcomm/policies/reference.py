"""Reference policies: the `oracle` that sets the target, and `random` play (SPEC section 6).

A policy is any callable from an `Observation` of B x n agents to `(moves (B, n), bits (B, n, K))`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from bitcomm.channel.core import bits_to_index, index_to_bits
from bitcomm.config import TaskConfig
from bitcomm.envs.core import N_MOVES
from bitcomm.envs.vec import Observation
from bitcomm.errors import bad_value

STAY, UP, DOWN, LEFT, RIGHT = range(5)


class Policy(Protocol):
    def __call__(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]: ...


def step_toward(row: np.ndarray, col: np.ndarray, to_row: np.ndarray, to_col: np.ndarray) -> np.ndarray:
    """One move along the axis with the larger distance (rows on a tie); stay when already there."""
    drow, dcol = to_row - row, to_col - col
    vertical = (np.abs(drow) >= np.abs(dcol)) & (drow != 0)
    move = np.where(dcol > 0, RIGHT, np.where(dcol < 0, LEFT, STAY))
    return np.where(vertical, np.where(drow > 0, DOWN, UP), move)


class OraclePolicy:
    """Sends the goal it sees as a K-bit cell index; steps toward the centre until its own goal has
    arrived (after `delay` steps), then walks a shortest path and stays. No error correction, so
    flipped or dropped bits send it astray: that is the point of measuring it under noise."""

    def __init__(self, task: TaskConfig) -> None:
        task.require_oracle_bits()
        self.task = task
        env, senders = task.env, task.slot_senders
        # the input slot that carries my own goal: a sender that sees it and sends it to me
        self.goal_slot = np.zeros(env.n_agents, dtype=np.int64)
        for x in range(env.n_agents):
            if x not in env.observed:  # no recipients can fix this: nobody has the goal to send
                raise bad_value("observes", env.observed, f"the oracle needs some agent to see the goal of agent {x}")
            slots = [k for k, j in enumerate(senders[x]) if j >= 0 and env.observed[j] == x]
            if not slots:
                raise bad_value(
                    "recipients",
                    task.recipient_lists,
                    f"the oracle needs agent {x} to hear an agent that sees its goal",
                )
            self.goal_slot[x] = slots[0]

    def __call__(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        S, C = self.task.env.size, self.task.env.cells
        B, n = obs.planes.shape[:2]
        flat = obs.planes.reshape(B, n, 2, C)
        pos, seen_goal = flat[:, :, 0].argmax(-1), flat[:, :, 1].argmax(-1)
        bits = index_to_bits(seen_goal, self.task.channel.bits)
        heard = obs.received[:, np.arange(n), self.goal_slot]  # (B, n, K)
        my_goal = np.minimum(bits_to_index(heard), C - 1)  # a corrupted index past the grid reads as the last cell
        known = (obs.t >= self.task.channel.delay)[:, None]
        row, col = np.divmod(pos, S)
        to_row, to_col = np.divmod(my_goal, S)
        centre = (S - 1) / 2  # between two cells on an even grid, so there is always a step toward it
        aim_row = np.where(known, to_row, centre)
        aim_col = np.where(known, to_col, centre)
        return step_toward(row, col, aim_row, aim_col), bits


class RandomPolicy:
    """Uniform moves and uniform bits."""

    def __init__(self, task: TaskConfig, seed: int | None = None) -> None:
        self.bits = task.channel.bits
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        B, n = obs.planes.shape[:2]
        moves = self.rng.integers(0, N_MOVES, size=(B, n))
        bits = self.rng.integers(0, 2, size=(B, n, self.bits), dtype=np.uint8)
        return moves, bits


REFERENCE_POLICIES = ("oracle", "random")


def make_reference_policy(name: str, task: TaskConfig, seed: int | None = None) -> Policy:
    if name == "oracle":
        return OraclePolicy(task)
    if name == "random":
        return RandomPolicy(task, seed)
    raise bad_value("policy", name, f"choose one of {', '.join(REFERENCE_POLICIES)}")
