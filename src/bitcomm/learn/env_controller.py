"""`EnvController`: a policy trained on a wrapped env (`bitcomm train --env`), acting in its user's own loop.

    controller = bitcomm.EnvController.load("runs/sl")   # a run folder or a .safetensors file
    env = controller.make_env()                          # the run's env in its BitChannel (or build your own)
    observations, infos = env.reset(seed=0)
    while env.agents:
        observations, rewards, terminations, truncations, infos = env.step(controller.act(observations))

`act` takes what `BitChannel.reset` and `step` return (agent -> `{"observation", "messages"}`) and gives what
`BitChannel.step` takes (agent -> `{"action", "message"}`), the action in the inner env's own space. In between
it does what `bitcomm.learn.env_rollout.play` does for one copy of a `VecEnv`, through the same functions (the
rows of `vector.agent_rows`, the network call, the sampling from one generator, `EnvLayout.clip` and
`vector.joint_action`), so that what is evaluated is what acts: an episode played through it on an env reset
with the seed `evaluate_env` gives its copy, sampling from a generator seeded as evaluation's, is that episode.
The grid's own policies act through `bitcomm.Controller`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pettingzoo import ParallelEnv

from bitcomm.config import Seed, check_bool
from bitcomm.envs.vector import EnvLayout, agent_rows, check_finite, joint_action
from bitcomm.errors import bad_value
from bitcomm.learn.env_config import EnvTrainConfig
from bitcomm.learn.env_eval import load_env_policy
from bitcomm.learn.env_rollout import env_factory
from bitcomm.policies.controller import sampling_generator, seeded_generator
from bitcomm.policies.mlp import MlpPolicy

KEYS = ("observation", "messages")
"""What each agent's observation holds in a `BitChannel`: the inner env's observation and the bits received."""


class EnvController:
    """The shared policy of a run on a wrapped env, acting for the agents present at each step of one episode."""

    def __init__(self, policy: MlpPolicy, config: EnvTrainConfig, seed: Seed = 0) -> None:
        self.policy = policy.eval()
        self.config = config
        """The run's `EnvTrainConfig`: its env, env kwargs and channel (what `make_env` builds)."""
        self.generator = seeded_generator(seed)  # as `Controller`'s

    @property
    def layout(self) -> EnvLayout:
        """The env's agents and spaces, as the network was built for them."""
        return self.policy.layout

    @classmethod
    def load(cls, path: str | Path, typed_env: str | None = None, seed: Seed = 0) -> EnvController:
        """From a run folder (its latest checkpoint) or a checkpoint file trained with `--env`; `seed` drives
        sampling. The recorded env is built once, to read its spaces, only if trusted: `typed_env` (the spec you
        trained with) or `BITCOMM_TRUST_ENVS` vouches for it (`load_env_policy`; docs/env_learning.md)."""
        cfg, policy = load_env_policy(path, typed_env)
        return cls(policy, cfg, seed)

    def make_env(self, drop_prob: float | None = None) -> ParallelEnv:
        """A fresh copy of the run's env in the `BitChannel` it was trained through (bits, delay, noise, topology,
        fixed actions; `drop_prob` replaces the drop probability). Close it when done."""
        return env_factory(self.config, drop_prob)()

    @torch.no_grad()
    def act(
        self, observations: Mapping[Any, Any], greedy: bool = False, generator: torch.Generator | None = None
    ) -> dict[Any, dict[str, Any]]:
        """agent -> `{"action", "message"}` for each agent of `observations` (what the `BitChannel` returned), the
        action in the inner env's space, the message K bits (uint8). Sampled, as the policy was trained, or with
        `greedy` the most likely action and message. Agents not in `observations` are absent, as in training: their
        rows read zeros, and their draws are made and dropped, so the sampling stream stays evaluation's."""
        L = self.layout
        self._check(observations)
        obs = np.zeros((1, L.n, L.obs_dim), np.float32)
        received = np.zeros((1, L.n, L.slots, L.bits), np.uint8)
        alive = np.zeros((1, L.n), bool)
        agent_rows(L, observations, set(observations), obs[0], received[0], alive[0])
        check_finite(L, obs)
        if not alive.any():  # nothing to act for: no network call, no draw (as `play` after every copy ended)
            return {}
        act_out, msg_logits = self.policy(torch.from_numpy(obs), torch.from_numpy(received))
        actions, bits = self.policy.draw(
            act_out, msg_logits, check_bool("greedy", greedy), sampling_generator(generator, self.generator)
        )
        present = [(i, a) for i, a in enumerate(L.agents) if alive[0, i]]
        return joint_action(L, L.clip(actions.numpy())[0], bits.numpy()[0], present)

    def _check(self, observations: Mapping[Any, Any]) -> None:
        """One line for an observation `BitChannel` would not have given: an agent the run's env does not have, a
        key missing, received bits of another shape or not 0 or 1 (the network would read them silently); an
        observation that does not fit its agent's space, or is not finite, is refused as `act` reads it
        (`vector.flat_row`, `vector.check_finite`), as in training."""
        L = self.layout
        if not isinstance(observations, Mapping):
            raise bad_value(
                "observations", type(observations).__name__, "must be a dict agent -> observation, as BitChannel's "
                "reset and step return",
            )  # fmt: skip
        for agent, ob in observations.items():
            where = f"observations[{agent!r}]"
            if agent not in L.agents:
                raise bad_value("agent", agent, f"the run's env has agents {list(L.agents)}")
            missing = [k for k in KEYS if not isinstance(ob, Mapping) or k not in ob]
            if missing:
                raise bad_value(
                    where, sorted(ob) if isinstance(ob, Mapping) else type(ob).__name__,
                    f"must be a dict with {' and '.join(map(repr, KEYS))} (as BitChannel returns); {missing[0]!r} "
                    "is missing",
                )  # fmt: skip
            bits = np.asarray(ob["messages"])
            if bits.shape != (L.slots, L.bits):
                raise bad_value(
                    f"{where}['messages'] shape", bits.shape, f"must be {(L.slots, L.bits)} (slots, bits per message)"
                )
            off = (bits != 0) & (bits != 1)  # the network reads uint8: a 0.5 or a NaN would be cast without a word
            if off.any():
                raise bad_value(f"{where}['messages']", bits[off].flat[0].item(), "every bit must be 0 or 1")
