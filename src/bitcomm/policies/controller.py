"""`Controller`: a trained policy for deployment, numpy in and numpy out, no training code needed.

    controller = bitcomm.Controller.load("runs/default")        # a run folder or a .safetensors file
    move, bits = controller.act(planes, received_bits)          # one agent: (2, S, S), (slots, K)
    moves, bits = controller.act(planes_batch, received_batch)  # N agents: (N, 2, S, S), (N, slots, K)

It acts through `bitcomm.policies.agent.act`, the function training rollouts and evaluation use, so what is
trained, measured and deployed cannot drift apart. Sampling is the default (how the policy was
trained); `greedy=True` takes the most likely move and message.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bitcomm.checkpoint import load_grid_weights
from bitcomm.config import Seed, TaskConfig, check_bool, check_seed
from bitcomm.errors import ConfigError, check_instance, one_line
from bitcomm.policies.agent import act
from bitcomm.policies.agent_policies import agent_batch
from bitcomm.policies.networks import ModelConfig, PolicyNet


def model_from_dict(d: dict[str, Any]) -> ModelConfig:
    names = {f.name for f in dataclasses.fields(ModelConfig)}
    values = {k: v for k, v in d.items() if k in names}
    if "conv_channels" in values:
        values["conv_channels"] = tuple(values["conv_channels"])
    return ModelConfig(**values)


def seeded_generator(seed: Seed) -> torch.Generator:
    """A torch generator seeded by `seed` (`Seed`); one error line for anything else, where torch takes -1 and
    refuses 2**64, a numpy integer or a string in words naming neither."""
    if seed is None:
        generator = torch.Generator()
        generator.seed()
        return generator
    if isinstance(seed, np.random.SeedSequence):
        seed = int(seed.generate_state(1, np.uint32)[0])
    return torch.Generator().manual_seed(check_seed(seed))


def sampling_generator(given: object, own: torch.Generator) -> torch.Generator:
    """The generator an `act` call samples from: `given`, else the controller's `own`; one line for anything else
    given, which torch refused deep in its sampling ("argument 'generator' must be torch.Generator, not int")."""
    if given is None:
        return own
    check_instance("generator", given, torch.Generator, "a torch.Generator, or None for the controller's own")
    return given  # type: ignore[return-value]


class Controller:
    """One shared policy network, acting for any agent of the task it was trained on."""

    def __init__(self, policy: PolicyNet, config: dict[str, Any], seed: Seed = 0, info: dict[str, Any] | None = None):
        self.policy = policy.eval()
        self.config = config
        """The training config as saved with the checkpoint (`TrainConfig.to_dict()`)."""
        self.info = info or {}
        """Checkpoint facts: path, episodes and batches trained."""
        self.generator = seeded_generator(seed)

    def with_seed(self, seed: Seed) -> Controller:
        """The same network (shared, not copied) sampling from a stream of its own seeded by `seed`: what a measure
        that must not depend on, or move, this controller's stream plays."""
        return Controller(self.policy, self.config, seed, self.info)

    @property
    def task(self) -> TaskConfig:
        return self.policy.task

    @property
    def messages(self) -> str:
        """The message head, "bitwise" or "onehot" (as `OnnxController.messages`)."""
        return self.policy.cfg.messages

    @classmethod
    def load(cls, path: str | Path, seed: Seed = 0) -> Controller:
        """From a run folder (its latest checkpoint) or a checkpoint file; `seed` (`Seed`) drives sampling."""
        weights, info = load_grid_weights(path)
        config = info["config"]
        try:
            # its random initial weights, replaced at once, must not draw from the caller's torch generator
            with torch.random.fork_rng(devices=[]):
                net = PolicyNet(TaskConfig.from_dict(config["task"]), model_from_dict(config["model"]))
            net.load_state_dict(weights["policy"])
        except (KeyError, TypeError, AttributeError, RuntimeError) as err:
            raise ConfigError(
                f"invalid checkpoint={info['path']!r}: weights do not fit its config ({one_line(err)})"
            ) from None
        return cls(net, config, seed, {k: v for k, v in info.items() if k != "config"})

    def act(
        self,
        planes: np.ndarray,
        received_bits: np.ndarray,
        greedy: bool = False,
        generator: torch.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """`(move, message_bits)`: int64 `()` and uint8 `(K,)` for one agent, `(N,)` and `(N, K)` for a batch."""
        planes, received, single = agent_batch(planes, received_bits, self.task)
        moves, bits, _, _ = act(
            self.policy,
            torch.from_numpy(np.ascontiguousarray(planes, dtype=np.uint8)),
            torch.from_numpy(np.ascontiguousarray(received, dtype=np.uint8)),
            greedy=check_bool("greedy", greedy),
            generator=sampling_generator(generator, self.generator),
        )
        m, b = moves.numpy().astype(np.int64), bits.numpy().astype(np.uint8)
        return (m[0], b[0]) if single else (m, b)
