"""`TrainConfig.update_dtype`: the update's passes in bfloat16 change the numbers a little, never the kind of
what is trained (float32 weights, float32 log-probabilities), and float32 is the update as it always was."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.learn.config import make_train_config
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector

TASK = TaskConfig(env=EnvConfig(size=4), channel=ChannelConfig(bits=4))


def one_update(dtype: str, estimator: str = "improved") -> tuple[Learner, dict[str, float]]:
    torch.manual_seed(0)
    cfg = make_train_config("reinforced", TASK, num_envs=16, update_dtype=dtype, estimator=estimator)
    learner, generator = Learner(cfg), torch.Generator().manual_seed(0)
    ro = Collector(cfg.training_task, cfg.num_envs).collect(learner.policy, np.random.SeedSequence(0), generator)
    return learner, learner.update(ro, generator)


@pytest.mark.parametrize("estimator", ["improved", "standard"])
def test_a_bfloat16_update_moves_the_weights_as_the_float32_one_does(estimator):
    before = make_train_config("reinforced", TASK)  # same seed: the same initial weights
    torch.manual_seed(0)
    start = {k: v.clone() for k, v in Learner(before).policy.state_dict().items()}
    (full, full_stats), (half, half_stats) = one_update("float32", estimator), one_update("bfloat16", estimator)
    steps: list[tuple[torch.Tensor, torch.Tensor]] = []
    for name, w in half.policy.state_dict().items():
        assert w.dtype == torch.float32
        step_full, step_half = full.policy.state_dict()[name] - start[name], w - start[name]
        if step_full.abs().max() > 0:
            steps.append((step_full.flatten(), step_half.flatten()))
            if w.dim() >= 2:  # each weight matrix moves the same way, to bfloat16's precision (a bias of a few
                # entries with gradients near zero may take Adam's full steps either way on a rounding)
                assert torch.nn.functional.cosine_similarity(*steps[-1], 0) > 0.9, name
    whole = [torch.cat(parts) for parts in zip(*steps, strict=True)]
    assert torch.nn.functional.cosine_similarity(*whole, 0) > 0.95  # and so does the policy as a whole
    assert all(p.dtype == torch.float32 for p in half.critic.parameters())
    assert half_stats["losses/value"] == pytest.approx(full_stats["losses/value"], rel=0.05)


def test_the_update_dtype_is_an_option_and_a_bad_one_is_one_line():
    with pytest.raises(ConfigError, match="update_dtype='float16'"):
        make_train_config("reinforced", update_dtype="float16")
    out = subprocess.run(
        [sys.executable, "-m", "bitcomm.cli", "train", "--update-dtype", "half", "--episodes", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "update_dtype='half'" in out.stderr and "Traceback" not in out.stderr
