"""`EnvTrainConfig`: a training run on any PettingZoo env wrapped in bitcomm's channel (SPEC section 8).

Plain JSON-able data, so config.json and a checkpoint's metadata rebuild the run: the env by its spec
`"package.module:factory"` and keyword arguments, the channel options of `BitChannel`, and the learning
options (the same names and meaning as the grid's `TrainConfig` where they exist). Defaults are the
synchronous PPO-style recipe of `reinforced`, sized for small vector-observation envs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from bitcomm.channel.topology import Edge
from bitcomm.config import check_seed, critic_passes, plain_fields
from bitcomm.envs.subproc_vector import check_workers
from bitcomm.errors import bad_value, check_int, check_number, check_rate, is_number
from bitcomm.learn.estimators import ESTIMATORS
from bitcomm.policies.heads import MESSAGE_HEADS, check_marginal_bits


@dataclass(frozen=True)
class EnvChannelConfig:
    """The channel options of `bitcomm.envs.channel_wrapper.BitChannel` (validated by it)."""

    bits: int = 7
    delay: int = 1
    flip_prob: float = 0.0
    drop_prob: float = 0.0
    topology: str | Sequence[Edge] = "all"
    """`all`, `ring`, or a list of `[sender, receiver]` agent-name pairs (a callable or a matrix is not JSON: pass
    one to `BitChannel` directly)."""
    fixed_actions: dict[str, Any] | None = None
    """Agents whose inner action the wrapper fixes (e.g. `{"speaker_0": 0}` silences MPE2's native speaker)."""

    def __post_init__(self) -> None:
        """Only what JSON cannot carry is checked here; `BitChannel` checks the values (names, K, delay, p)."""
        plain_fields(self)
        edges = self.topology
        if not isinstance(edges, str) and not (
            isinstance(edges, (list, tuple))
            and all(isinstance(e, (list, tuple)) and len(e) == 2 and all(isinstance(a, str) for a in e) for e in edges)
        ):
            raise bad_value(
                "topology", edges, "all, ring, or a list of [sender, receiver] agent-name pairs, each name a string as "
                "JSON writes it (\"0\" for an agent 0)",
            )  # fmt: skip
        if self.fixed_actions is not None and not isinstance(self.fixed_actions, dict):
            raise bad_value("fixed_actions", self.fixed_actions, "a JSON object: agent name -> its fixed action")


@dataclass(frozen=True)
class EnvTrainConfig:
    env: str
    """The env factory, `"package.module:factory"`, e.g. `mpe2.simple_speaker_listener_v4:parallel_env`."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    channel: EnvChannelConfig = field(default_factory=EnvChannelConfig)
    estimator: str = "improved"
    """`standard` (paper eq. 7) or `improved` (paper eq. 8, with multi-recipient credit: SPEC section 8)."""
    messages: str = "bitwise"
    """Message head: `bitwise` or `onehot`."""
    episodes: int = 20_000
    seed: int = 0
    num_envs: int = 32
    """Episodes per batch (copies of the env stepped together)."""
    env_workers: int = 0
    """0: the copies are stepped in the learner's process; W >= 1: split over W worker processes (for slow
    envs; the episodes, and so the run, are the same)."""
    lr: float = 1e-3
    critic_lr: float = 1e-3
    gamma: float = 0.95
    epochs: int = 4
    critic_epochs: int = 0
    """Passes of the critic over each batch, in the first of the `epochs` (0: every epoch), as the grid's
    `TrainConfig.critic_epochs`."""
    minibatches: int = 4
    clip: float = 0.2
    """PPO ratio clipping for the reused batch; 0: the plain policy gradient."""
    adv_norm: bool = True
    entropy_action: float = 0.01
    entropy_message: float = 0.01
    entropy_message_marginal: float = 0.0
    """Weight of the entropy of the minibatch's average message distribution (as the grid's
    `TrainConfig.entropy_message_marginal`); needs K <= 12."""
    max_grad_norm: float = 1.0
    hidden: tuple[int, ...] = (128, 128)
    """Widths of the policy's trunk and of the critic's body."""
    obs_norm: bool = False
    """Standardise the policy's observations and the critic's state by running statistics
    (`bitcomm.policies.mlp.RunningNorm`), updated after each learning update."""
    checkpoint_seconds: float = 60.0
    keep_checkpoints: int = 3

    def __post_init__(self) -> None:
        plain_fields(self)
        if self.estimator not in ESTIMATORS:
            raise bad_value("estimator", self.estimator, f"choose one of {', '.join(ESTIMATORS)}")
        if self.messages not in MESSAGE_HEADS:
            raise bad_value("messages", self.messages, f"choose one of {', '.join(MESSAGE_HEADS)}")
        if not isinstance(self.env_kwargs, dict):
            raise bad_value("env-kwargs", self.env_kwargs, "must be a JSON object")
        for name in ("episodes", "num_envs", "epochs", "minibatches", "keep_checkpoints"):
            check_int(name, getattr(self, name), 1)
        check_seed(self.seed)
        check_workers(self.env_workers, self.num_envs, 0)
        if self.minibatches > self.num_envs:
            raise bad_value("minibatches", self.minibatches, f"at most num_envs ({self.num_envs})")
        critic_passes(self.critic_epochs, self.epochs)
        for name in ("lr", "critic_lr"):
            check_rate(name, getattr(self, name))
        check_number("max_grad_norm", self.max_grad_norm, 0.0, strict=True)
        for name in ("clip", "entropy_action", "entropy_message", "entropy_message_marginal", "checkpoint_seconds"):
            check_number(name, getattr(self, name), 0.0)
        check_marginal_bits(self.entropy_message_marginal, self.channel.bits)
        if not (is_number(self.gamma) and 0.0 < self.gamma <= 1.0):
            raise bad_value("gamma", self.gamma, "must be in (0, 1]")
        object.__setattr__(self, "hidden", tuple(self.hidden))
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in self.hidden):
            raise bad_value("hidden", self.hidden, "one or more integers >= 1")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EnvTrainConfig:
        d = dict(d)
        channel = EnvChannelConfig(**d.pop("channel"))
        return cls(channel=channel, **{k: v for k, v in d.items() if k in _FIELDS})


_FIELDS = {f.name for f in dataclasses.fields(EnvTrainConfig)}
