"""One agent's policy, as a robot would hold it: its own planes and received bits in, a move and K bits out.

The batched `Policy` of `bitcomm.policies.reference` sees all B x n agents at once, which is what the simulator
wants but not what a deployed robot has. `AgentPolicy` is the per-agent view every runtime shares:
`bitcomm deploy` runs one per process, `bitcomm render`/`analyze`/`sweep` run it through
`BatchedPolicy`, so the policy that is measured in the simulator is the one that is deployed.

The interface is batched over a leading axis N of independent agent-steps (N = 1 for a robot):
`act(planes (N, 2, S, S), received (N, slots, K), t (N,), agent (N,)) -> (moves (N,), bits (N, K))`.
`t` (steps already taken in the episode) and `agent` (the agent's index) are given because reference
policies need them: the oracle knows its goal only `delay` steps into the episode, and which input slot
carries its goal depends on the agent. A learned `Controller` ignores both (it is reactive and shared).
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from bitcomm.channel.core import bits_to_index, index_to_bits
from bitcomm.config import TaskConfig
from bitcomm.envs.core import N_MOVES
from bitcomm.envs.vec import Observation
from bitcomm.errors import ConfigError
from bitcomm.policies.reference import OraclePolicy, step_toward


class AgentPolicy(Protocol):
    """What one agent needs to act; see the module docstring for shapes."""

    task: TaskConfig

    def act(
        self, planes: np.ndarray, received: np.ndarray, t: np.ndarray, agent: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...


def agent_batch(planes: np.ndarray, received: np.ndarray, task: TaskConfig) -> tuple[np.ndarray, np.ndarray, bool]:
    """`(planes (N, 2, S, S), received (N, slots, K), single)` from the inputs of one agent or of N agents.

    `single` says a leading axis was added (one agent's `(2, S, S)` and `(slots, K)`), so a controller
    can answer in the shape it was asked; shapes that fit neither, or an entry other than 0 or 1, stop with one
    error line.
    """
    planes, received = np.asarray(planes), np.asarray(received)
    single = planes.ndim == 3
    if single:
        planes, received = planes[None], received[None]
    S, K, slots = task.env.size, task.channel.bits, task.slots
    if planes.shape[1:] != (2, S, S) or received.shape[1:] != (slots, K) or planes.shape[0] != received.shape[0]:
        raise ConfigError(
            f"invalid input shapes planes={planes.shape}, received_bits={received.shape}: "
            f"expected (N, 2, {S}, {S}) and (N, {slots}, {K}) (or without N for one agent)"
        )
    for name, x in (("planes", planes), ("received_bits", received)):
        off = (x != 0) & (x != 1)  # the networks read 0/1: a 0.5 or a NaN would be cast or read without a word
        if off.any():
            raise ConfigError(f"invalid {name} value {x[off].flat[0].item()!r}: every entry must be 0 or 1")
    return planes, received, single


class OracleAgent:
    """The oracle of `bitcomm.policies.reference.OraclePolicy`, one agent at a time (same moves, same bits).

    It sends the goal it sees as a K-bit cell index, heads for the grid's centre until its own goal
    can have arrived (`t >= delay`), then walks to the cell the received bits name.
    """

    def __init__(self, task: TaskConfig) -> None:
        self.task = task
        self.goal_slot = OraclePolicy(task).goal_slot  # checks the task suits the oracle, once

    def act(
        self, planes: np.ndarray, received: np.ndarray, t: np.ndarray, agent: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        S, C = self.task.env.size, self.task.env.cells
        N = planes.shape[0]
        flat = planes.reshape(N, 2, C)
        pos, seen_goal = flat[:, 0].argmax(-1), flat[:, 1].argmax(-1)
        bits = index_to_bits(seen_goal, self.task.channel.bits)
        heard = received[np.arange(N), self.goal_slot[np.asarray(agent, dtype=np.int64)]]
        my_goal = np.minimum(bits_to_index(heard), C - 1)  # as the batched oracle: past the grid reads as last cell
        known = np.asarray(t) >= self.task.channel.delay
        row, col = np.divmod(pos, S)
        to_row, to_col = np.divmod(my_goal, S)
        centre = (S - 1) / 2
        return step_toward(row, col, np.where(known, to_row, centre), np.where(known, to_col, centre)), bits


class RandomAgent:
    """Uniform moves and uniform bits, from its own seeded stream."""

    def __init__(self, task: TaskConfig, seed: int | np.random.SeedSequence | None = None) -> None:
        self.task = task
        self.rng = np.random.default_rng(seed)

    def act(
        self, planes: np.ndarray, received: np.ndarray, t: np.ndarray, agent: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        N = planes.shape[0]
        moves = self.rng.integers(0, N_MOVES, size=(N,), dtype=np.int64)
        return moves, self.rng.integers(0, 2, size=(N, self.task.channel.bits), dtype=np.uint8)


class ControllerAgent:
    """A learned `bitcomm.Controller` as an `AgentPolicy`: it needs neither `t` nor the agent index.

    `Controller.act(planes, received_bits, greedy)` takes numpy arrays, batched or not, and returns
    `(move, message_bits)`; this wrapper only fixes the dtypes the runtimes expect.
    """

    def __init__(self, controller: Any, greedy: bool = False) -> None:
        self.controller = controller
        self.task: TaskConfig = controller.task
        self.greedy = greedy

    def act(
        self, planes: np.ndarray, received: np.ndarray, t: np.ndarray, agent: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        moves, bits = self.controller.act(planes, received, greedy=self.greedy)
        N = planes.shape[0]
        return (
            np.asarray(moves, dtype=np.int64).reshape(N),
            np.asarray(bits, dtype=np.uint8).reshape(N, self.task.channel.bits),
        )


class BatchedPolicy:
    """An `AgentPolicy` as a batched `Policy` (Observation of B x n agents -> moves (B, n), bits (B, n, K)).

    Every agent-step is one row of one `act` call, so a batch costs one call whatever B and n are.
    """

    def __init__(self, agent_policy: AgentPolicy) -> None:
        self.agent_policy = agent_policy

    def __call__(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        B, n, _, S, _ = obs.planes.shape
        slots, K = obs.received.shape[2:]
        moves, bits = self.agent_policy.act(
            obs.planes.reshape(B * n, 2, S, S),
            obs.received.reshape(B * n, slots, K),
            np.repeat(np.asarray(obs.t), n),
            np.tile(np.arange(n), B),
        )
        return np.asarray(moves).reshape(B, n), np.asarray(bits, dtype=np.uint8).reshape(B, n, K)
