"""One evaluator for every policy: mean episode length with a 95% interval, return, success.

The episode set is fixed by the seed: slot k of chunk c always starts from the same cells with
the same goals, whatever the policy, so two policies evaluated with one seed face the same
episodes. Each slot counts its first episode only; counting whichever episodes finish first
would favour short ones.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from bitcomm.config import TaskConfig
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import bad_value
from bitcomm.policies import Policy

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
    def from_episodes(cls, lengths: np.ndarray, returns: np.ndarray, success: np.ndarray) -> EvalResult:
        n = len(lengths)
        mean = float(np.mean(lengths))
        half = 1.96 * float(np.std(lengths, ddof=1)) / math.sqrt(n) if n > 1 else 0.0
        return cls(n, mean, (mean - half, mean + half), float(np.mean(returns)), float(np.mean(success)))


def run_first_episodes(
    policy: Policy, task: TaskConfig, episodes: int, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Play the seeded episode set; return per-episode lengths, team returns and successes."""
    lengths = np.zeros(episodes, dtype=np.int64)
    returns = np.zeros(episodes, dtype=np.float64)
    success = np.zeros(episodes, dtype=bool)
    chunks = math.ceil(episodes / EVAL_CHUNK)
    for c, chunk_seed in enumerate(np.random.SeedSequence(seed).spawn(chunks)):
        lo = c * EVAL_CHUNK
        b = min(EVAL_CHUNK, episodes - lo)
        env = VecGoalExchange(task, b, seed=chunk_seed)
        pending = np.ones(b, dtype=bool)
        while pending.any():
            moves, bits = policy(env.observe())
            result, _ = env.step(moves, bits)
            fin = result.finished
            first = pending[fin.index]
            idx = fin.index[first]
            lengths[lo + idx] = fin.length[first]
            returns[lo + idx] = fin.team_return[first]
            success[lo + idx] = fin.success[first]
            pending[idx] = False
    return lengths, returns, success


def evaluate(policy: Policy, task: TaskConfig, episodes: int = 2000, seed: int = 0) -> EvalResult:
    """Mean episode length (95% interval), mean team return and success rate over a seeded set."""
    if not isinstance(episodes, int) or episodes < 1:
        raise bad_value("episodes", episodes, "must be an integer >= 1")
    return EvalResult.from_episodes(*run_first_episodes(policy, task, episodes, seed))
