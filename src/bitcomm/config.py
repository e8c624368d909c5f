"""Configuration of the task: the grid world (SPEC section 1) and the channel (SPEC section 2).

Defaults live here and only here. Every value is validated when the dataclass is built, so a
bad value fails early with one line that names it (see `bitcomm.errors`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, TypeAlias

import numpy as np

from bitcomm.errors import bad_value, check_instance, is_integer, is_number

MAX_SEED = 2**32 - 1
"""Seeds feed numpy's SeedSequence and torch.manual_seed; 32 bits is what both take everywhere."""

MAX_EVAL_EPISODES = 10_000_000
"""Evaluation keeps 17 bytes per episode and plays 4,096 at a time: 10^7 is 170 MB and hours of CPU."""

MAX_SIZE = 1024
"""Grid side cap: a 1024 x 1024 grid is 2 MB of planes per agent and episode; commands also check memory."""
MAX_AGENTS = 64
"""Agents cap: every agent's network sees 2n state planes and each step costs n forward passes."""
MAX_STEPS = 100_000
"""Episode length cap (`max_steps`): beyond it a random policy's evaluation would run for days."""
MAX_JOBS = 1024
"""Processes or threads at once (`--jobs`, `--threads`, `OnnxController.load(threads=)`)."""


Integer: TypeAlias = int | np.integer
"""A Python or a numpy integer (`rng.integers()` gives one): what a seed or an episode count takes (`check_seed`)."""

Seed: TypeAlias = Integer | np.random.SeedSequence | None
"""What a deployed policy's sampling stream takes (`Controller`, `EnvController`, `OnnxController`): an integer
(Python's or numpy's), a `SeedSequence` (one spawned per robot, say), or None for fresh entropy from the OS (two robots
loaded with one int draw the same numbers)."""


def check_seed(value: object) -> int:
    """`value` as a Python int, or one error line unless it is a seed every stream takes (an integer in [0,
    MAX_SEED]): numpy's SeedSequence refuses a negative one and torch's manual_seed one past 64 bits, each in words
    naming neither, and torch's manual_seed a numpy integer."""
    if not is_integer(value) or not 0 <= value <= MAX_SEED:  # type: ignore[operator]
        raise bad_value("seed", value, f"must be an integer in [0, {MAX_SEED}]")
    return int(value)  # type: ignore[call-overload]


def critic_passes(critic_epochs: object, epochs: int) -> int:
    """The passes the critics make over a batch, the first of the policy's `epochs` (`critic_epochs` 0: all of
    them), or one error line unless `critic_epochs` is an integer in [0, epochs]."""
    if not is_integer(critic_epochs) or not 0 <= critic_epochs <= epochs:  # type: ignore[operator]
        raise bad_value("critic-epochs", critic_epochs, f"must be an integer in [0, epochs ({epochs})]; 0: every epoch")
    return int(critic_epochs) or epochs  # type: ignore[call-overload]


def check_evaluation(episodes: object, seed: object) -> tuple[int, int]:
    """`(episodes, seed)` as Python ints, or one error line unless an evaluation can play `episodes` (an integer >= 1;
    0 was an IndexError from an empty batch) seeded by `seed` (`check_seed`)."""
    if not is_integer(episodes) or episodes < 1:  # type: ignore[operator]
        raise bad_value("episodes", episodes, "must be an integer >= 1")
    return int(episodes), check_seed(seed)  # type: ignore[call-overload]


def entries(name: str, value: object, allowed: str) -> tuple[Any, ...]:
    """`value`'s entries as a tuple, or one error line naming it where it has none (a number where a sequence goes),
    rather than Python's "'int' object is not iterable", which names nothing."""
    try:
        return tuple(value)  # type: ignore[call-overload,arg-type]
    except TypeError:
        raise bad_value(name, value, allowed) from None


def plain_fields(config: Any) -> None:
    """Store each numpy scalar of a config dataclass (a value from `np.arange`, a sweep's array) as the Python value
    it is, so that the config stays JSON (a run's config.json and checkpoints: json refuses numpy's int64 and float32)
    and seeds torch (whose `manual_seed` refuses a numpy integer); then one error line for a `bool` option that is
    not a bool, where a string such as "no" would read as true."""
    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, np.generic):
            value = value.item()
            object.__setattr__(config, f.name, value)
        if f.type in ("bool", bool):
            check_bool(f.name.replace("_", "-"), value)


def check_bool(name: str, value: object) -> bool:
    """`value` as a bool, or one error line unless it is True or False (numpy's too): a string such as "no" or "False"
    would read as true."""
    if not isinstance(value, (bool, np.bool_)):
        raise bad_value(name, value, "must be True or False")
    return bool(value)


def _probability(config: object, field: str, name: str) -> None:
    """One error line unless `config.field` is a number in [0, 1] (a numpy one is taken; a bool is not); stored
    as a Python float, so a config stays JSON."""
    value = getattr(config, field)
    if not (is_number(value) and 0.0 <= float(value) <= 1.0):  # type: ignore[arg-type]
        raise bad_value(name, value, "must be a probability in [0, 1]")
    object.__setattr__(config, field, float(value))  # type: ignore[arg-type]


def _count(config: object, field: str, name: str, least: int, most: int, why: str) -> None:
    """One error line unless `config.field` is an integer in [least, most] (a numpy one is taken; a bool is not);
    stored as a Python int. `why` explains the bounds."""
    value = getattr(config, field)
    if not is_integer(value) or not least <= value <= most:
        raise bad_value(name, value, f"must be an integer in [{least}, {most}] ({why})")
    object.__setattr__(config, field, int(value))


def recipient_matrix(recipients: tuple[tuple[int, ...], ...], n_agents: int) -> np.ndarray:
    """Boolean `(n, n)` from one tuple of recipients per sender: `[j, x]` is True when x receives j's message."""
    mat = np.zeros((n_agents, n_agents), dtype=bool)
    for j, rec in enumerate(recipients):
        mat[j, list(rec)] = True
    return mat


def slot_table(recipients: np.ndarray) -> np.ndarray:
    """`(n, slots)` int from a recipient matrix: the sender heard in each input slot of each agent, -1 for none.

    An agent's message input holds one K-bit slot per sender it hears, ordered by sender index; `slots`
    is the largest number of senders any agent hears (at least 1, so every agent has an input).
    """
    n = recipients.shape[0]
    senders = [np.flatnonzero(recipients[:, x]) for x in range(n)]
    table = -np.ones((n, max(1, max(len(s) for s in senders))), dtype=np.int64)
    for x, s in enumerate(senders):
        table[x, : len(s)] = s
    return table


MIN_DELAY = 1
"""A message sent at step t arrives at t + 1 at the earliest."""


def check_arrival(delay: int, steps: int, steps_name: str, why: str = "") -> None:
    """One line unless a message sent at an episode's first step arrives within its `steps` (`steps_name`: max_steps,
    or training's train_max_steps). Where `delay` is already `MIN_DELAY` the line names the steps, the value that can
    change: `train --max-steps 1` was blamed on a default delay the user never typed; else it names `delay` (`why`
    follows its line)."""
    if delay < steps:
        return
    if delay == MIN_DELAY:
        raise bad_value(steps_name, steps, f"must be > delay ({MIN_DELAY}): a message must arrive within an episode")
    raise bad_value("delay", delay, f"must be < {steps_name} ({steps}){why}")


@dataclass(frozen=True)
class EnvConfig:
    """The goal-exchange grid world (SPEC section 1)."""

    size: int = 10
    """The grid is `size x size` cells."""
    n_agents: int = 2
    """Agents share the grid and may stand on the same cell."""
    max_steps: int = 256
    """An episode is truncated after this many steps."""
    observes: tuple[int, ...] | None = None
    """`observes[i]` is the agent whose goal agent `i` sees; None means the ring `(i + 1) % n`."""
    act_fail_prob: float = 0.0
    """Actuation noise: probability that a chosen move is not executed (the agent stays); 0 in the paper."""
    act_delay: int = 0
    """Actuation noise: moves take effect this many steps after they are chosen (stay before that)."""

    def __post_init__(self) -> None:
        _count(self, "size", "size", 2, MAX_SIZE, "cells a side")
        _count(self, "n_agents", "agents", 2, MAX_AGENTS, "at least 2 agents are needed")
        _count(self, "max_steps", "max_steps", 1, MAX_STEPS, "steps before an episode is truncated")
        _probability(self, "act_fail_prob", "act_fail_prob")
        _count(self, "act_delay", "act_delay", 0, self.max_steps - 1, "a move must take effect within max_steps")
        if self.observes is not None:
            obs = entries("observes", self.observes, f"needs one entry per agent ({self.n_agents})")
            if len(obs) != self.n_agents:
                raise bad_value("observes", obs, f"needs one entry per agent ({self.n_agents})")
            for i, j in enumerate(obs):
                if not is_integer(j) or not 0 <= j < self.n_agents:
                    raise bad_value("observes", obs, f"entries must be agents 0..{self.n_agents - 1}")
                if i == j:
                    raise bad_value(
                        "observes", obs, f"agent {i} may not observe its own goal (any other agent is allowed)"
                    )
            object.__setattr__(self, "observes", tuple(int(j) for j in obs))

    @property
    def observed(self) -> tuple[int, ...]:
        """Whose goal each agent sees, with the ring default filled in."""
        if self.observes is not None:
            return self.observes
        return tuple((i + 1) % self.n_agents for i in range(self.n_agents))

    @property
    def cells(self) -> int:
        return self.size * self.size


@dataclass(frozen=True)
class ChannelConfig:
    """The discrete, noisy message channel (SPEC section 2)."""

    bits: int = 7
    """Message size K; the channel always carries K bits."""
    recipients: tuple[tuple[int, ...], ...] | None = None
    """`recipients[j]`: the agents that receive agent j's message; None means the agent whose goal j sees."""
    delay: int = 1
    """A message sent at step t is received at step t + delay; before that the input is zeros."""
    flip_prob: float = 0.0
    """Each bit is flipped independently with this probability in transit."""
    drop_prob: float = 0.0
    """Each message is lost with this probability (received as all zeros, by every recipient)."""

    def __post_init__(self) -> None:
        _count(self, "bits", "bits", 1, 30, "bits a message carries")
        _count(self, "delay", "delay", MIN_DELAY, MAX_STEPS, "a message arrives one step later at the earliest")
        _probability(self, "flip_prob", "flip_prob")
        _probability(self, "drop_prob", "drop_prob")
        if self.recipients is not None:
            try:
                rows = tuple(tuple(r) for r in self.recipients)
            except TypeError:  # a number where a list goes, which Python calls "not iterable", naming nothing
                raise bad_value(
                    "recipients", self.recipients, "one list of recipient agents per sender, e.g. [[1], [0]]"
                ) from None
            if not all(is_integer(x) for r in rows for x in r):
                raise bad_value("recipients", rows, "entries must be agent indices (integers)")
            object.__setattr__(self, "recipients", tuple(tuple(int(x) for x in r) for r in rows))

    @property
    def messages(self) -> int:
        """Size of the message space, 2^K."""
        return 1 << self.bits


@dataclass(frozen=True)
class TaskConfig:
    """The environment and its channel together, with the checks that need both."""

    env: EnvConfig = field(default_factory=EnvConfig)
    channel: ChannelConfig = field(default_factory=ChannelConfig)

    def __post_init__(self) -> None:
        check_instance("env", self.env, EnvConfig, "a bitcomm.EnvConfig, e.g. EnvConfig(size=4)")
        check_instance("channel", self.channel, ChannelConfig, "a bitcomm.ChannelConfig, e.g. ChannelConfig(bits=4)")
        check_arrival(self.channel.delay, self.env.max_steps, "max_steps", ": a message must arrive within an episode")
        n = self.env.n_agents
        recipients = self.recipient_lists
        if len(recipients) != n:
            raise bad_value("recipients", recipients, f"needs one entry per agent ({n})")
        for j, rec in enumerate(recipients):
            if len(rec) == 0 or len(set(rec)) != len(rec):
                raise bad_value("recipients", recipients, "each agent sends to one or more distinct agents")
            for x in rec:
                if not 0 <= x < n or x == j:
                    raise bad_value("recipients", recipients, f"recipients must be other agents in 0..{n - 1}")

    def to_dict(self) -> dict[str, Any]:
        """Plain values for JSON: checkpoints, the deploy wire and exported policy cards carry the task this way."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TaskConfig:
        """Inverse of `to_dict`; JSON's lists (`observes`, `recipients`) become tuples in the configs' own checks."""
        return cls(EnvConfig(**d["env"]), ChannelConfig(**d["channel"]))

    @property
    def recipient_lists(self) -> tuple[tuple[int, ...], ...]:
        if self.channel.recipients is not None:
            return self.channel.recipients
        return tuple((x,) for x in self.env.observed)

    @property
    def recipient_matrix(self) -> np.ndarray:
        """Boolean `(n, n)`: `[j, x]` is True when x receives j's message."""
        return recipient_matrix(self.recipient_lists, self.env.n_agents)

    @property
    def slot_senders(self) -> np.ndarray:
        """`(n, slots)` int: the sender heard in each input slot of each agent, -1 for none.

        An agent's message input holds one K-bit slot per sender it hears, ordered by sender index;
        `slots` is the largest number of senders any agent hears (1 in the paper).
        """
        return slot_table(self.recipient_matrix)

    @property
    def slots(self) -> int:
        return int(self.slot_senders.shape[1])

    def require_oracle_bits(self) -> None:
        """The oracle names a goal cell in K bits, so it needs 2^K >= size^2."""
        need = math.ceil(math.log2(self.env.cells))
        if self.channel.bits < need:
            raise bad_value(
                "bits",
                self.channel.bits,
                f"the oracle needs at least {need} bits to name one of {self.env.cells} cells",
            )
