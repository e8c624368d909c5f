"""Measure a policy trained on a wrapped env: mean team return and episode length over seeded episodes.

Episodes are played in chunks of B first episodes, chunk c seeded by `SeedSequence(seed, spawn_key=(c,))`
and sampling from a generator seeded with `seed`, so two policies measured with one seed face the same
episodes. Intervals are 95% Student's t intervals over episodes (`bitcomm.stats`; an env's own episode
length and return ranges are unknown here, so they are not cut to them). `drop_prob` replaces
the channel's drop probability (1 cuts the channel: the learned no-communication level of the same network).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from bitcomm.checkpoint import load_env_weights
from bitcomm.config import Integer, check_evaluation
from bitcomm.envs.factory import check_recorded_env
from bitcomm.errors import ConfigError, one_line
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.learn.env_rollout import make_vec, play
from bitcomm.learn.run_folder import config_of
from bitcomm.policies.mlp import MlpPolicy
from bitcomm.stats import mean_interval

EVAL_CHUNK = 256
"""Episodes played side by side."""


@dataclass(frozen=True)
class EnvEvalResult:
    episodes: int
    mean_team_return: float
    return_ci95: tuple[float, float]
    mean_episode_length: float
    length_ci95: tuple[float, float]

    def to_dict(self) -> dict[str, object]:
        out = asdict(self)
        out["return_ci95"], out["length_ci95"] = list(self.return_ci95), list(self.length_ci95)
        return out


def _interval(x: np.ndarray) -> tuple[float, tuple[float, float]]:
    mean, low, high = (float(v) for v in mean_interval(x))
    return mean, (low, high)


def chunk_seed(seed: int, chunk: int) -> np.random.SeedSequence:
    """The episodes of evaluation chunk `chunk` (so `bitcomm render` can replay the first one)."""
    return np.random.SeedSequence(seed, spawn_key=(chunk,))


def load_env_policy(path: Path | str, typed_env: str | None = None) -> tuple[EnvTrainConfig, MlpPolicy]:
    """The config and policy of a wrapped-env checkpoint (a run folder: its latest). The env it records is built
    only if trusted (`check_recorded_env`): `typed_env` is the spec the caller's user typed, if any. A grid run is
    one line (`bitcomm.Controller` reads those)."""
    weights, info = load_env_weights(path)
    cfg = config_of(info["path"], info["config"], EnvTrainConfig.from_dict)
    check_recorded_env(cfg.env, info["path"], typed_env)
    with make_vec(cfg, 1) as vec:  # one copy, to read the layout; closed, as an env may hold a window or files
        layout = vec.layout
    with torch.random.fork_rng(devices=[]):  # its random initial weights, replaced at once: the caller's draws stay
        policy = MlpPolicy(layout, cfg.messages, cfg.hidden, cfg.obs_norm)
    try:
        policy.load_state_dict(weights["policy"])
    except (KeyError, RuntimeError) as err:
        raise ConfigError(
            f"invalid checkpoint={info['path']!r}: weights do not fit its config ({one_line(err)})"
        ) from None
    return cfg, policy.eval()


def evaluate_env(
    path: Path | str,
    episodes: Integer,
    seed: Integer,
    drop_prob: float | None = None,
    greedy: bool = False,
    typed_env: str | None = None,
) -> EnvEvalResult:
    """Play `episodes` seeded episodes with the policy of `path` on its env (channel drops changed by `drop_prob`;
    `typed_env` as in `load_env_policy`)."""
    episodes, seed = check_evaluation(episodes, seed)  # before the env is built
    cfg, policy = load_env_policy(path, typed_env)
    return evaluate_env_policy(cfg, policy, episodes, seed, drop_prob, greedy)


def evaluate_env_policy(
    cfg: EnvTrainConfig,
    policy: MlpPolicy,
    episodes: Integer,
    seed: Integer,
    drop_prob: float | None = None,
    greedy: bool = False,
) -> EnvEvalResult:
    """`evaluate_env` for a policy `load_env_policy` read (so `bitcomm eval` can check, from its layout, that
    `min(episodes, EVAL_CHUNK)` episodes side by side fit before they play)."""
    episodes, seed = check_evaluation(episodes, seed)  # Python ints: torch's manual_seed refuses a numpy one
    generator = torch.Generator().manual_seed(seed)
    returns: list[np.ndarray] = []
    lengths: list[np.ndarray] = []
    chunk = 0
    with make_vec(cfg, min(episodes, EVAL_CHUNK), drop_prob) as vec:
        while sum(len(r) for r in returns) < episodes:
            ro = play(vec, policy, chunk_seed(seed, chunk), generator, greedy=greedy, flag="episodes")
            returns.append(ro.team_return)
            lengths.append(ro.length)
            chunk += 1
    ret, ret_ci = _interval(np.concatenate(returns)[:episodes])
    length, len_ci = _interval(np.concatenate(lengths)[:episodes].astype(np.float64))
    return EnvEvalResult(episodes, ret, ret_ci, length, len_ci)
