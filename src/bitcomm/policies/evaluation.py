"""One evaluator for every policy: mean episode length with a 95% interval (Student's t, cut to the 1 to
max_steps an episode can last), return, success.

The episode set is fixed by the seed: slot k of chunk c always starts from the same cells with
the same goals, whatever the policy, so two policies evaluated with one seed face the same
episodes. Each slot counts its first episode only; counting whichever episodes finish first
would favour short ones.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from bitcomm.config import Integer, TaskConfig, check_evaluation
from bitcomm.envs.core import N_MOVES, StepResult
from bitcomm.envs.vec import Observation, VecGoalExchange
from bitcomm.errors import ConfigError, bad_value
from bitcomm.policies.reference import Policy
from bitcomm.stats import mean_interval

if TYPE_CHECKING:
    from bitcomm.policies.controller import Controller

EVAL_CHUNK = 4096


@dataclass(frozen=True)
class EvalResult:
    episodes: int
    mean_episode_length: float
    ci95: tuple[float, float]
    mean_team_return: float
    success_rate: float

    def to_dict(self) -> dict[str, object]:
        out = asdict(self)
        out["ci95"] = list(self.ci95)
        return out

    @classmethod
    def from_episodes(cls, lengths: np.ndarray, returns: np.ndarray, success: np.ndarray, max_steps: int) -> EvalResult:
        """The figures of episodes that each lasted 1 to `max_steps` steps."""
        mean, low, high = (float(x) for x in mean_interval(lengths, bounds=(1, max_steps)))
        return cls(len(lengths), mean, (low, high), float(np.mean(returns)), float(np.mean(success)))


class FirstEpisodeStep(NamedTuple):
    """One step of the B first episodes: what was done and what came of it. (What the policy saw is not kept:
    the environment's observation buffers are live, so by the time a step is yielded they already show the
    state after it, and a slot that just ended shows its next episode's start.)"""

    moves: np.ndarray
    bits: np.ndarray
    result: StepResult
    dropped: np.ndarray
    active: np.ndarray  # (B,) bool, the slot was still in its first episode at this step


def play_first_episodes(env: VecGoalExchange, policy: Policy) -> Iterator[FirstEpisodeStep]:
    """Step `env` with `policy` until every slot's first episode has ended (later ones are ignored)."""
    active = np.ones(env.num_envs, dtype=bool)
    while active.any():
        obs = env.observe()
        moves, bits = policy(obs)
        result, dropped = env.step(moves, bits)
        yield FirstEpisodeStep(moves, bits, result, dropped, active.copy())
        active[result.finished.env_index] = False


def seeded_episode_envs(task: TaskConfig, episodes: int, seed: int) -> Iterator[tuple[int, VecGoalExchange]]:
    """The fixed episode set of `seed`: chunks of up to EVAL_CHUNK fresh slots, with their offsets.

    Slot k's first episode is the set's episode `offset + k`; anything that must play the same
    episodes as `evaluate` (the UDP deployment, say) takes them from here.
    """
    for c, chunk_seed in enumerate(np.random.SeedSequence(seed).spawn(math.ceil(episodes / EVAL_CHUNK))):
        lo = c * EVAL_CHUNK
        yield lo, VecGoalExchange(task, min(EVAL_CHUNK, episodes - lo), seed=chunk_seed)


def checked(policy: Policy, task: TaskConfig) -> Policy:
    """`policy` with each answer checked against what the env takes, `(B, n)` moves in [0, N_MOVES) and `(B, n, K)`
    bits of 0 or 1, so that a policy of the user's own is one error line naming what it returned: a move of -1 was
    the last move (numpy's negative index), 1.5 a move cast to 1 and a bit of 2 a bit sent as 1, without a word; a
    move of 7 or a shape of another task numpy's IndexError or broadcast error."""
    n, K = task.env.n_agents, task.channel.bits

    def play(obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        answer = policy(obs)
        B = obs.planes.shape[0]
        if not isinstance(answer, tuple) or len(answer) != 2:
            raise bad_value("policy output", type(answer).__name__, "must be a (moves, bits) pair")
        moves, bits = np.asarray(answer[0]), np.asarray(answer[1])
        if moves.shape != (B, n) or bits.shape != (B, n, K):
            raise ConfigError(
                f"invalid policy output shapes moves={moves.shape}, bits={bits.shape}: expected ({B}, {n}) and "
                f"({B}, {n}, {K}) for {B} episodes of {n} agents and {K}-bit messages"
            )
        bad_move = ~np.isin(moves, np.arange(N_MOVES))
        if bad_move.any():
            raise bad_value("policy move", moves[bad_move].flat[0].item(), f"every move must be 0 to {N_MOVES - 1}")
        bad_bit = (bits != 0) & (bits != 1)
        if bad_bit.any():
            raise bad_value("policy bit", bits[bad_bit].flat[0].item(), "every bit must be 0 or 1")
        return moves.astype(np.int64, copy=False), bits.astype(np.uint8, copy=False)

    return play


def run_first_episodes(
    policy: Policy, task: TaskConfig, episodes: int, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Play the seeded episode set; return per-episode lengths, team returns and successes."""
    policy = checked(policy, task)
    lengths = np.zeros(episodes, dtype=np.int64)
    returns = np.zeros(episodes, dtype=np.float64)
    success = np.zeros(episodes, dtype=bool)
    for lo, env in seeded_episode_envs(task, episodes, seed):
        for step in play_first_episodes(env, policy):
            fin = step.result.finished
            first = step.active[fin.env_index]
            idx = lo + fin.env_index[first]
            lengths[idx], returns[idx], success[idx] = fin.length[first], fin.team_return[first], fin.success[first]
    return lengths, returns, success


def evaluate(
    policy: Policy | Controller, task: TaskConfig | None = None, episodes: Integer = 2000, seed: Integer = 0
) -> EvalResult:
    """Mean episode length (95% interval), mean team return and success rate over a seeded set.

    `policy` is a batched `Policy` (an `Observation` in, `(B, n)` moves and `(B, n, K)` bits out) or a trained
    `bitcomm.Controller`, which samples by `seed` (`evaluate_controller` plays it greedily) and brings its task:
    `evaluate(Controller.load("runs/demo"))`. Any other policy needs `task`."""
    episodes, seed = check_evaluation(episodes, seed)
    if not callable(policy):
        from bitcomm.policies.controller import Controller

        if not isinstance(policy, Controller):
            raise bad_value("policy", policy, "must be a bitcomm.Controller or a callable obs -> (moves, bits)")
        return evaluate_controller(policy, episodes, seed, task=task)
    if not isinstance(task, TaskConfig):
        raise bad_value("task", task, "must be a bitcomm.TaskConfig (the task to play the policy on)")
    from bitcomm.policies.denormals import flush_denormals  # torch: not at import, which `bitcomm --help` does

    with flush_denormals():  # as training does: the same numbers its checks measured, without the slow path
        return EvalResult.from_episodes(*run_first_episodes(policy, task, episodes, seed), task.env.max_steps)


def evaluate_checkpoint(
    path: str | Path, episodes: Integer = 2000, seed: Integer = 0, greedy: bool = False, task: TaskConfig | None = None
) -> EvalResult:
    """`evaluate` for a trained policy (run folder or checkpoint file), acting through `Controller` as
    `bitcomm eval` and a deployed robot do; `task` defaults to the one it was trained on."""
    from bitcomm.policies.controller import Controller

    return evaluate_controller(Controller.load(path, seed=seed), episodes, seed, greedy, task)


def evaluate_controller(
    controller: Controller, episodes: Integer, seed: Integer, greedy: bool = False, task: TaskConfig | None = None
) -> EvalResult:
    """`evaluate` for a `bitcomm.Controller` (loaded, or wrapping a policy in training); `task` defaults to the one it
    was trained on. It samples from a generator seeded by `seed`, as `Controller.load(path, seed)` starts, not from the
    controller's own: the figure is a function of the policy and `seed`, the same each time a notebook cell reruns,
    and the controller's generator goes on where it was."""
    from bitcomm.policies.agent_policies import BatchedPolicy, ControllerAgent

    if task is not None:
        check_inputs_fit(task, controller.task)
    seeded = controller.with_seed(seed)
    return evaluate(BatchedPolicy(ControllerAgent(seeded, greedy=greedy)), task or controller.task, episodes, seed)


def check_inputs_fit(task: object, trained: TaskConfig) -> None:
    """One line naming the task where its agents' inputs are not the shape the policy was trained on (the grid's
    size, the bits, the senders an agent hears), rather than the shapes of a batch the task plays (`invalid input
    shapes planes=(20, 2, 4, 4)`), which name neither task."""
    if not isinstance(task, TaskConfig):
        raise bad_value("task", task, "must be a bitcomm.TaskConfig (the task to play the policy on)")
    for name, now, was in (
        ("size", task.env.size, trained.env.size),
        ("bits", task.channel.bits, trained.channel.bits),
        ("slots", task.slots, trained.slots),  # the senders an agent hears: its network's message inputs
    ):
        if now != was:
            raise bad_value(f"task {name}", now, f"the policy was trained with {name}={was}, the shape of its inputs")
