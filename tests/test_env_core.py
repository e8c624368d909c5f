"""The grid world of SPEC section 1, checked against hand-computed numbers."""

from __future__ import annotations

import numpy as np
import pytest

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.core import GoalExchangeCore
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import ConfigError

STAY, UP, DOWN, LEFT, RIGHT = range(5)


def cell(row: int, col: int, size: int = 10) -> int:
    return row * size + col


def place(core: GoalExchangeCore, pos: list[list[int]], goal: list[list[int]]) -> None:
    """Put every episode's agents and goals on chosen cells (planes redrawn to match)."""
    idx = np.arange(core.num_envs)
    core._draw_planes(idx, 0)
    core.pos[:] = np.asarray(pos)
    core.goal[:] = np.asarray(goal)
    core._draw_planes(idx, 1)


def one_hot_planes(cells: np.ndarray, size: int) -> np.ndarray:
    """`(..., )` cell indices -> `(..., size, size)` one-hot planes."""
    return np.eye(size * size, dtype=np.uint8)[cells].reshape(*cells.shape, size, size)


def assert_planes_match(core: GoalExchangeCore) -> None:
    """The incrementally kept planes equal planes rebuilt from positions and goals."""
    S, n = core.cfg.size, core.cfg.n_agents
    observed = np.asarray(core.cfg.observed)
    np.testing.assert_array_equal(core.obs[:, :, 0], one_hot_planes(core.pos, S))
    np.testing.assert_array_equal(core.obs[:, :, 1], one_hot_planes(core.goal[:, observed], S))
    np.testing.assert_array_equal(core.state[:, :n], one_hot_planes(core.pos, S))
    np.testing.assert_array_equal(core.state[:, n:], one_hot_planes(core.goal, S))


# ---------------------------------------------------------------- rewards


@pytest.mark.parametrize(
    ("start", "goal", "move", "reward"),
    [
        ((5, 5), (5, 8), RIGHT, -0.3 + 0.2),  # closer
        ((5, 5), (5, 8), LEFT, -0.3),  # farther
        ((5, 5), (5, 8), UP, -0.3),  # sideways: distance 3 -> 4
        ((5, 5), (5, 8), STAY, -0.3 - 0.1),  # stay
        ((0, 0), (5, 8), UP, -0.3 - 0.1),  # off the grid: invalid, stays in place
        ((9, 9), (5, 8), RIGHT, -0.3 - 0.1),  # off the grid on the other side
        ((5, 7), (5, 8), RIGHT, 0.0),  # onto the goal
        ((6, 8), (5, 8), UP, 0.0),  # onto the goal from below
    ],
)
def test_reward_of_one_move(start: tuple[int, int], goal: tuple[int, int], move: int, reward: float) -> None:
    core = GoalExchangeCore(EnvConfig(), num_envs=1, seed=0)
    far = cell(0, 9)  # agent 1 stays far from its goal, so the episode goes on
    place(core, [[cell(*start), cell(9, 0)]], [[cell(*goal), far]])
    result = core.step(np.array([[move, STAY]]))
    np.testing.assert_allclose(result.rewards[0], [reward, -0.4], atol=1e-6)
    np.testing.assert_allclose(result.team_reward[0], reward - 0.4, atol=1e-6)
    assert result.rewards.dtype == np.float32


def test_moves_follow_row_column_convention() -> None:
    core = GoalExchangeCore(EnvConfig(n_agents=4), num_envs=1, seed=0)
    start = cell(4, 4)
    place(core, [[start] * 4], [[cell(0, 0)] * 4])
    core.step(np.array([[UP, DOWN, LEFT, RIGHT]]))
    np.testing.assert_array_equal(core.pos[0], [cell(3, 4), cell(5, 4), cell(4, 3), cell(4, 5)])
    assert_planes_match(core)  # several agents on one cell, then apart again


def test_resting_on_goal_is_free_and_leaving_it_costs() -> None:
    core = GoalExchangeCore(EnvConfig(), num_envs=1, seed=0)
    place(core, [[cell(2, 2), cell(7, 7)]], [[cell(2, 2), cell(7, 9)]])
    result = core.step(np.array([[STAY, LEFT]]))
    np.testing.assert_allclose(result.rewards[0], [0.0, -0.3], atol=1e-6)
    result = core.step(np.array([[DOWN, STAY]]))  # leaves its goal: farther, no idle penalty
    np.testing.assert_allclose(result.rewards[0], [-0.3, -0.4], atol=1e-6)
    assert not result.terminated[0]


# ---------------------------------------------------------------- episode ends


def test_termination_when_all_on_goal_then_self_reset() -> None:
    core = GoalExchangeCore(EnvConfig(), num_envs=3, seed=0)
    # episode 0: both one step from goal; episode 1: only agent 0; episode 2: far away
    place(
        core,
        [[cell(5, 7), cell(8, 9)], [cell(5, 7), cell(0, 0)], [cell(0, 0), cell(0, 1)]],
        [[cell(5, 8), cell(9, 9)], [cell(5, 8), cell(9, 9)], [cell(9, 9), cell(9, 8)]],
    )
    core.step(np.array([[STAY, STAY]] * 3))  # step 1: -0.8 in every episode
    result = core.step(np.array([[RIGHT, DOWN], [RIGHT, DOWN], [RIGHT, DOWN]]))
    np.testing.assert_array_equal(result.terminated, [True, False, False])
    np.testing.assert_array_equal(result.truncated, [False, False, False])
    np.testing.assert_allclose(result.rewards[0], [0.0, 0.0], atol=1e-6)
    fin = result.finished
    np.testing.assert_array_equal(fin.env_index, [0])
    np.testing.assert_array_equal(fin.length, [2])
    np.testing.assert_allclose(fin.team_return, [-0.8 + 0.0], atol=1e-6)
    np.testing.assert_array_equal(fin.success, [True])
    # episode 0 started afresh: step counter, return, new cells, planes; the others went on
    np.testing.assert_array_equal(core.t, [0, 2, 2])
    assert core.ep_return[0] == 0.0
    assert (core.pos[0] != core.goal[0]).all()
    assert_planes_match(core)


def test_truncation_at_max_steps() -> None:
    core = GoalExchangeCore(EnvConfig(max_steps=3), num_envs=2, seed=1)
    for step in range(3):
        result = core.step(np.zeros((2, 2), dtype=np.int64))  # staying never reaches a goal (start != goal)
        if step < 2:
            assert result.finished.env_index.size == 0
            assert not result.truncated.any()
    np.testing.assert_array_equal(result.truncated, [True, True])
    np.testing.assert_array_equal(result.terminated, [False, False])
    fin = result.finished
    np.testing.assert_array_equal(fin.env_index, [0, 1])
    np.testing.assert_array_equal(fin.length, [3, 3])
    np.testing.assert_allclose(fin.team_return, [3 * -0.8] * 2, atol=1e-5)
    np.testing.assert_array_equal(fin.success, [False, False])
    np.testing.assert_array_equal(core.t, [0, 0])


def test_autoreset_off_keeps_terminal_state_until_reset() -> None:
    core = GoalExchangeCore(EnvConfig(), num_envs=2, seed=0, autoreset=False)
    place(
        core,
        [[cell(5, 7), cell(8, 9)], [cell(0, 0), cell(0, 1)]],
        [[cell(5, 8), cell(9, 9)], [cell(9, 9), cell(9, 8)]],
    )
    result = core.step(np.array([[RIGHT, DOWN], [STAY, STAY]]))
    np.testing.assert_array_equal(result.finished.env_index, [0])
    np.testing.assert_array_equal(core.pos[0], core.goal[0])  # the terminal observation is still there
    np.testing.assert_array_equal(core.t, [1, 1])
    assert_planes_match(core)
    core.reset(np.array([True, False]))
    np.testing.assert_array_equal(core.t, [0, 1])
    assert (core.pos[0] != core.goal[0]).all()
    assert_planes_match(core)


def test_random_play_keeps_planes_consistent_and_reports_every_episode() -> None:
    cfg = EnvConfig(size=4, n_agents=3, max_steps=20)
    B = 256
    core = GoalExchangeCore(cfg, num_envs=B, seed=2)
    rng = np.random.default_rng(0)
    started = np.zeros(B, dtype=np.int64)
    finished = 0
    for _ in range(200):
        t_before = core.t.copy()
        result = core.step(rng.integers(0, 5, size=(B, 3)))
        fin = result.finished
        np.testing.assert_array_equal(fin.length, t_before[fin.env_index] + 1)
        assert (fin.length <= cfg.max_steps).all()
        np.testing.assert_array_equal(fin.success, result.terminated[fin.env_index])
        done = result.terminated | result.truncated
        np.testing.assert_array_equal(np.flatnonzero(done), fin.env_index)
        started[fin.env_index] += 1
        finished += fin.env_index.size
        assert (core.pos != core.goal).any(axis=1).all()  # new and running episodes are never already won
        assert_planes_match(core)
    assert finished == started.sum() > B  # many episodes ended, terminated and truncated alike
    assert 0 < np.mean(core.t) < cfg.max_steps


# ---------------------------------------------------------------- reset and observations


def test_start_is_never_own_goal_and_cells_are_uniform() -> None:
    cfg = EnvConfig(size=3, n_agents=2)
    core = GoalExchangeCore(cfg, num_envs=20000, seed=3)
    assert (core.pos != core.goal).all()
    counts = np.bincount(core.goal.ravel(), minlength=9)
    expected = core.goal.size / 9
    assert np.abs(counts - expected).max() < 5 * np.sqrt(expected)
    pairs = np.bincount((core.pos * 9 + core.goal).ravel(), minlength=81).reshape(9, 9)
    assert (np.diag(pairs) == 0).all() and (pairs + np.eye(9, dtype=np.int64) > 0).all()


def test_observation_planes_are_own_position_and_observed_goal() -> None:
    core = GoalExchangeCore(EnvConfig(), num_envs=1, seed=0)
    place(core, [[cell(1, 2), cell(3, 4)]], [[cell(5, 6), cell(7, 8)]])
    obs = core.obs[0]
    assert obs.shape == (2, 2, 10, 10) and obs.dtype == np.uint8
    assert obs[0, 0, 1, 2] == 1 and obs[0, 0].sum() == 1  # agent 0 sees itself
    assert obs[0, 1, 7, 8] == 1 and obs[0, 1].sum() == 1  # ... and agent 1's goal
    assert obs[1, 0, 3, 4] == 1 and obs[1, 0].sum() == 1
    assert obs[1, 1, 5, 6] == 1 and obs[1, 1].sum() == 1
    assert obs[0, 1, 5, 6] == 0 and obs[1, 1, 7, 8] == 0  # never its own goal
    state = core.state[0]
    assert state.shape == (4, 10, 10)
    assert state[0, 1, 2] == state[1, 3, 4] == state[2, 5, 6] == state[3, 7, 8] == 1
    assert state.sum() == 4


def test_observes_map() -> None:
    cfg = EnvConfig(n_agents=3, observes=(2, 0, 1))
    core = GoalExchangeCore(cfg, num_envs=8, seed=4)
    for b in range(8):
        for i, j in enumerate((2, 0, 1)):
            seen = np.flatnonzero(core.obs[b, i, 1])
            np.testing.assert_array_equal(seen, [core.goal[b, j]])
    assert_planes_match(core)


@pytest.mark.parametrize(
    ("make", "names"),
    [
        (lambda: EnvConfig(size=True), "size=True"),
        (lambda: EnvConfig(act_fail_prob=True), "act_fail_prob=True"),
        (lambda: EnvConfig(observes=(True, False)), "observes"),
        (lambda: ChannelConfig(bits=True), "bits=True"),
        (lambda: ChannelConfig(flip_prob=np.bool_(True)), "flip_prob"),
        (lambda: ChannelConfig(recipients=((1.7,), (0,))), "recipients"),
    ],
)
def test_a_bool_or_a_fraction_is_not_a_count_or_an_agent(make, names: str) -> None:
    """True is an int to Python and 1.7 truncates to one: the task's configs refuse both, in one line."""
    with pytest.raises(ConfigError, match=f"invalid {names}"):
        make()


@pytest.mark.parametrize(
    ("make", "names"),
    [
        (lambda: TaskConfig(env=4), "env=4: must be a bitcomm.EnvConfig"),
        (lambda: TaskConfig(EnvConfig(), EnvConfig()), r"channel=EnvConfig\(.*must be a bitcomm.ChannelConfig"),
        (lambda: VecGoalExchange(None, 8), "task=None: must be a bitcomm.TaskConfig"),
        (lambda: VecGoalExchange(TaskConfig(), 0), "num_envs=0: must be an integer >= 1"),
        (lambda: VecGoalExchange(TaskConfig(), "8"), "num_envs='8'"),
        (lambda: VecGoalExchange(TaskConfig(), 8, seed=-1), "seed=-1: must be None, an integer >= 0"),
        # a number where a list goes was Python's "'int' object is not iterable", naming nothing
        (lambda: EnvConfig(observes=1), "observes=1: needs one entry per agent"),
        (lambda: ChannelConfig(recipients=[1, 0]), r"recipients=\[1, 0\]: one list of recipient agents per sender"),
        (lambda: ChannelConfig(recipients=3), "recipients=3: one list"),
    ],
)
def test_a_value_of_the_wrong_kind_is_named_in_one_line(make, names: str) -> None:
    """Not an AttributeError from inside the core, nor numpy's "expected non-negative integer" naming nothing."""
    with pytest.raises(ConfigError, match=f"invalid {names}"):
        make()
    assert VecGoalExchange(TaskConfig(), np.int64(2), seed=np.uint32(5)).num_envs == 2


def test_numpy_numbers_are_taken_and_stored_as_python_ones() -> None:
    """A config built from numpy values is the config of the same Python values (and JSON as it is)."""
    env = EnvConfig(size=np.int64(4), max_steps=np.int32(20), act_fail_prob=np.float32(0.5), observes=np.array([1, 0]))
    channel = ChannelConfig(bits=np.int64(4), delay=np.int8(2), drop_prob=np.float64(0.25))
    assert env == EnvConfig(size=4, max_steps=20, act_fail_prob=0.5, observes=(1, 0))
    assert channel == ChannelConfig(bits=4, delay=2, drop_prob=0.25)
    assert {type(v) for v in (env.size, env.max_steps, channel.bits, channel.delay)} == {int}
    assert {type(v) for v in (env.act_fail_prob, channel.drop_prob)} == {float}


# ---------------------------------------------------------------- actuation noise


def test_act_fail_prob_one_means_nobody_moves() -> None:
    core = GoalExchangeCore(EnvConfig(act_fail_prob=1.0), num_envs=16, seed=5)
    start = core.pos.copy()
    rng = np.random.default_rng(0)
    for _ in range(10):
        result = core.step(rng.integers(1, 5, size=(16, 2)))
        np.testing.assert_allclose(result.rewards, -0.4, atol=1e-6)  # a cancelled move counts as staying
    np.testing.assert_array_equal(core.pos, start)


def test_act_fail_prob_rate() -> None:
    core = GoalExchangeCore(EnvConfig(act_fail_prob=0.25), num_envs=4096, seed=6)
    place(core, [[cell(5, 5), cell(5, 5)]] * 4096, [[cell(0, 0), cell(0, 0)]] * 4096)
    core.step(np.full((4096, 2), UP))
    moved = (core.pos != cell(5, 5)).mean()
    assert abs(moved - 0.75) < 0.02


def test_act_delay_shifts_moves_by_k_steps() -> None:
    core = GoalExchangeCore(EnvConfig(act_delay=2), num_envs=1, seed=0)
    place(core, [[cell(5, 5), cell(5, 5)]], [[cell(0, 0), cell(9, 9)]])
    chosen = [[RIGHT, LEFT], [DOWN, UP], [STAY, STAY], [STAY, STAY]]
    expected_pos = [[cell(5, 5)] * 2, [cell(5, 5)] * 2, [cell(5, 6), cell(5, 4)], [cell(6, 6), cell(4, 4)]]
    expected_reward = [[-0.4, -0.4], [-0.4, -0.4], [-0.3, -0.3], [-0.3, -0.3]]
    for moves, pos, reward in zip(chosen, expected_pos, expected_reward, strict=True):
        result = core.step(np.array([moves]))
        np.testing.assert_array_equal(core.pos[0], pos)
        np.testing.assert_allclose(result.rewards[0], reward, atol=1e-6)


def test_act_delay_queue_is_cleared_on_episode_reset() -> None:
    core = GoalExchangeCore(EnvConfig(act_delay=1, max_steps=2), num_envs=1, seed=0)
    core.step(np.array([[STAY, STAY]]))
    core.step(np.array([[RIGHT, RIGHT]]))  # chosen on the last step: must not act in the next episode
    assert core.t[0] == 0
    start = core.pos.copy()
    core.step(np.array([[STAY, STAY]]))
    np.testing.assert_array_equal(core.pos, start)


# ---------------------------------------------------------------- seeding


def test_seeded_runs_are_identical_and_seeds_differ() -> None:
    def run(seed: int, cfg: EnvConfig) -> list[np.ndarray]:
        core = GoalExchangeCore(cfg, num_envs=64, seed=seed)
        rng = np.random.default_rng(0)
        out = [core.pos.copy(), core.goal.copy()]
        for _ in range(30):
            result = core.step(rng.integers(0, 5, size=(64, 2)))
            out += [result.rewards, core.pos.copy(), core.goal.copy()]
        return out

    cfg = EnvConfig(max_steps=10, act_fail_prob=0.3)
    a, b, c = run(7, cfg), run(7, cfg), run(8, cfg)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])
    # actuation noise draws from its own stream: the task's first draws do not depend on it
    np.testing.assert_array_equal(run(7, EnvConfig(max_steps=10))[1], a[1])
