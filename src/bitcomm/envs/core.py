"""Vectorized goal-exchange grid world: B independent episodes stepped as arrays (SPEC section 1).

Every agent starts on a random cell and has a random goal cell (start != goal). Agent i observes
two one-hot planes: its own position and the goal of agent `observed[i]`; never its own goal.
Critics see the full state: every agent's position, then every goal.

Moves: 0 stay, 1 up (row - 1), 2 down (row + 1), 3 left (column - 1), 4 right (column + 1).
A move off the grid leaves the agent in place and counts as invalid.
Reward of agent i after all moved: 0 on its goal; otherwise -0.3, +0.2 if its Manhattan distance
shrank, -0.1 if it stayed or moved invalidly. Agents are trained on the team reward (the sum).
An episode terminates once every agent is on its goal and is truncated after `max_steps`.
Episodes reset themselves when they end (unless `autoreset=False`, which leaves a finished episode in
its terminal state until `reset` is called: the PettingZoo view needs that); `step` reports the ones
that finished.

Actuation noise (beyond the paper, default off): with `act_fail_prob` a chosen move is not executed
(the agent stays), and with `act_delay` moves take effect that many steps late (stay before). The
reward applies to what actually happened: a move that was not executed counts as staying.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from bitcomm.config import EnvConfig

N_MOVES = 5
MOVE_NAMES = ("stay", "up", "down", "left", "right")
DROW = np.array([0, -1, 1, 0, 0], dtype=np.int64)
DCOL = np.array([0, 0, 0, -1, 1], dtype=np.int64)

STEP_PENALTY, CLOSER_BONUS, IDLE_PENALTY = -0.3, 0.2, -0.1


class FinishedEpisodes(NamedTuple):
    """Episodes that ended at this step: their batch slots and their figures."""

    env_index: np.ndarray  # (F,) int, which of the B episodes ended (`index` would shadow `tuple.index`)
    length: np.ndarray  # (F,) int, steps taken
    team_return: np.ndarray  # (F,) float, undiscounted sum of team rewards
    success: np.ndarray  # (F,) bool, every agent on its goal before truncation


class StepResult(NamedTuple):
    rewards: np.ndarray  # (B, n) float32, per-agent reward
    team_reward: np.ndarray  # (B,) float32
    terminated: np.ndarray  # (B,) bool
    truncated: np.ndarray  # (B,) bool
    finished: FinishedEpisodes


class GoalExchangeCore:
    """B episodes of the grid world; arrays in, arrays out, no Python loop over episodes or agents."""

    def __init__(
        self,
        cfg: EnvConfig,
        num_envs: int,
        seed: int | np.random.SeedSequence | None = None,
        autoreset: bool = True,
    ) -> None:
        self.cfg = cfg
        self.num_envs = B = num_envs
        self.autoreset = autoreset
        n, S = cfg.n_agents, cfg.size
        self.observed = np.asarray(cfg.observed, dtype=np.int64)
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        task_seed, noise_seed = seq.spawn(2)
        self.rng = np.random.default_rng(task_seed)  # starts and goals
        self.noise_rng = np.random.default_rng(noise_seed)  # actuation noise, so it never shifts the task's draws
        self.pos = np.zeros((B, n), dtype=np.int64)  # cell index row * size + column
        self.goal = np.zeros((B, n), dtype=np.int64)
        self.t = np.zeros(B, dtype=np.int64)
        self.ep_return = np.zeros(B, dtype=np.float64)
        # planes kept up to date incrementally: only the cells that change are touched each step
        self.obs = np.zeros((B, n, 2, S, S), dtype=np.uint8)
        self.state = np.zeros((B, 2 * n, S, S), dtype=np.uint8)
        self._obs_flat = self.obs.reshape(B, n, 2, S * S)
        self._state_flat = self.state.reshape(B, 2 * n, S * S)
        self._pending = np.zeros((cfg.act_delay, B, n), dtype=np.int64)  # moves not yet executed
        self._clock = 0
        self._rows = np.arange(B)[:, None]
        self._agents = np.arange(n)[None, :]
        self.reset()

    # ------------------------------------------------------------------ reset
    def reset(self, mask: np.ndarray | None = None) -> None:
        """Start new episodes in the slots of `mask` (every slot when None)."""
        idx = np.arange(self.num_envs) if mask is None else np.flatnonzero(mask)
        if idx.size == 0:
            return
        n, C = self.cfg.n_agents, self.cfg.cells
        start = self.rng.integers(0, C, size=(idx.size, n))
        goal = (start + 1 + self.rng.integers(0, C - 1, size=(idx.size, n))) % C  # uniform over cells != start
        self.begin(idx, start, goal)

    def begin(self, idx: np.ndarray, start: np.ndarray, goal: np.ndarray) -> None:
        """Start episodes in slots `idx` from given `(len(idx), n)` start and goal cells (no draw)."""
        self._draw_planes(idx, 0)
        self.pos[idx], self.goal[idx] = start, goal
        self.t[idx] = 0
        self.ep_return[idx] = 0.0
        self._pending[:, idx] = 0
        self._draw_planes(idx, 1)

    def _draw_planes(self, idx: np.ndarray, value: int) -> None:
        """Write `value` at the occupied cells of the episodes `idx` (0 clears them before a reset)."""
        n = self.cfg.n_agents
        rows, agents = idx[:, None], self._agents
        self._obs_flat[rows, agents, 0, self.pos[idx]] = value
        self._obs_flat[rows, agents, 1, self.goal[idx][:, self.observed]] = value
        self._state_flat[rows, agents, self.pos[idx]] = value
        self._state_flat[rows, n + agents, self.goal[idx]] = value

    # ------------------------------------------------------------------ step
    def step(self, moves: np.ndarray) -> StepResult:
        """Apply `(B, n)` chosen moves; finished episodes are reported, then reset (if `autoreset`)."""
        cfg = self.cfg
        S = cfg.size
        executed = np.asarray(moves, dtype=np.int64)
        if cfg.act_delay > 0:
            slot = self._clock % cfg.act_delay
            executed, self._pending[slot] = self._pending[slot].copy(), executed
        self._clock += 1
        if cfg.act_fail_prob > 0.0:
            executed = np.where(self.noise_rng.random(executed.shape) < cfg.act_fail_prob, 0, executed)

        row, col = np.divmod(self.pos, S)
        grow, gcol = np.divmod(self.goal, S)
        nrow, ncol = row + DROW[executed], col + DCOL[executed]
        inside = (nrow >= 0) & (nrow < S) & (ncol >= 0) & (ncol < S)
        nrow, ncol = np.where(inside, nrow, row), np.where(inside, ncol, col)
        d_old = np.abs(row - grow) + np.abs(col - gcol)
        d_new = np.abs(nrow - grow) + np.abs(ncol - gcol)
        on_goal = d_new == 0
        reward = STEP_PENALTY + CLOSER_BONUS * (d_new < d_old) + IDLE_PENALTY * ((executed == 0) | ~inside)
        reward = np.where(on_goal, 0.0, reward).astype(np.float32)

        # move the position marks: clear old cells, set new ones
        new_pos = nrow * S + ncol
        rows, agents = self._rows, self._agents
        self._obs_flat[rows, agents, 0, self.pos] = 0
        self._state_flat[rows, agents, self.pos] = 0
        self.pos = new_pos
        self._obs_flat[rows, agents, 0, new_pos] = 1
        self._state_flat[rows, agents, new_pos] = 1

        team = reward.sum(axis=1)
        self.t += 1
        self.ep_return += team
        terminated = on_goal.all(axis=1)
        truncated = ~terminated & (self.t >= cfg.max_steps)
        done = terminated | truncated
        idx = np.flatnonzero(done)
        finished = FinishedEpisodes(idx, self.t[idx].copy(), self.ep_return[idx].copy(), terminated[idx].copy())
        if idx.size and self.autoreset:
            self.reset(done)
        return StepResult(reward, team, terminated, truncated, finished)
