"""B copies of a channel-wrapped PettingZoo env stepped together, as arrays over `(B, n, ...)`.

The learner speaks arrays; a wrapped env (`bitcomm.envs.channel_wrapper.BitChannel`) speaks dicts keyed by
agent name. This module is the one place that converts, so nothing above it loops over agents:

- observations `(B, n, D)` float32: each agent's inner observation flattened and zero-padded to the widest
  (`EnvLayout.obs_sizes` holds each agent's true size); zeros for an agent that is not present. A Box is
  flattened as it is; any other space gymnasium can flatten (Discrete, MultiDiscrete and MultiBinary as
  one-hots and bits, Dict and Tuple of those) by `gymnasium.spaces.flatten`;
- actions: Discrete ones as indices from 0 (the space's `start` is added on the way in); MultiDiscrete and
  MultiBinary ones as one index over all their combinations (at most `MAX_JOINT_ACTIONS`; unravelled on the
  way in), so the learner's categorical head acts on them unchanged; Box ones as flat vectors (reshaped to
  the space's shape and dtype on the way in);
- received messages `(B, n, slots, K)` uint8, as the wrapper delivers them;
- the critic's state `(B, Ds)` float32: the inner env's `state()` where it has a `state_space`, or, where it
  has none, every agent's padded observation concatenated (`n * D`);
- `alive (B, n)`: the agent is present (in `env.agents`) and acts at this step;
- rewards `(B, n)`, `dropped (B, n)` (the message the agent sent this step was lost), `ended (B,)`.

The inner envs are Python objects stepped one at a time, so the loop over the B copies stays; an env
whose episode has ended is not stepped again until the next `reset`. Where that loop is the bottleneck (a slow
env), `bitcomm.envs.subproc_vector.SubprocVecEnv` runs shares of the copies, each a `VecEnv`, in worker
processes; `WrappedEnvMaker` is the picklable maker both build their copies with.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, NamedTuple

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from bitcomm.envs.channel_wrapper import BitChannel, possible_agents_of
from bitcomm.envs.factory import make_parallel_env
from bitcomm.errors import bad_value, one_line

MAX_JOINT_ACTIONS = 4096
"""A MultiDiscrete or MultiBinary action space is learned as one categorical over its combinations: this many at
most (MultiBinary(12), MultiDiscrete([16, 16, 16]))."""


@dataclass(frozen=True, eq=False)
class EnvLayout:
    """The shapes a wrapped env's arrays take, read once from its spaces: what the networks are built for."""

    agents: tuple[str, ...]
    obs_sizes: tuple[int, ...]
    """Each agent's flattened inner observation size (padded to `obs_dim` in the arrays)."""
    slots: int
    bits: int
    delay: int
    discrete: bool
    """True: every agent's inner action is Discrete (or MultiDiscrete, MultiBinary); False: every one is a Box."""
    action_sizes: tuple[int, ...]
    """Discrete: each agent's number of actions (combinations); Box: each agent's flattened action size."""
    low: np.ndarray
    """(n, action_dim) Box lower bounds (padding 0); unused for Discrete."""
    high: np.ndarray
    state_size: int
    has_state: bool
    """The inner env has `state()`; otherwise the state is the concatenated padded observations."""
    fixed: np.ndarray
    """(n,) bool: agents whose inner action the wrapper fixes (`fixed_actions`): their action head learns nothing."""
    recipients: np.ndarray
    """(n, n) bool: [j, x] = x hears j."""
    obs_spaces: tuple[spaces.Space, ...] = ()
    """Each agent's inner observation space (what `flat_observation` flattens; `of` fills it)."""
    action_spaces: tuple[spaces.Space, ...] = ()
    """Each agent's inner action space (what `inner_action` converts to; `of` fills it)."""

    @property
    def n(self) -> int:
        return len(self.agents)

    @property
    def obs_dim(self) -> int:
        return max(self.obs_sizes)

    @property
    def action_dim(self) -> int:
        return max(self.action_sizes)

    @property
    def action_mask(self) -> np.ndarray:
        """(n, action_dim) bool: which actions (Discrete) or dimensions (Box) each agent has."""
        return np.arange(self.action_dim)[None, :] < np.asarray(self.action_sizes)[:, None]

    def clip(self, actions: np.ndarray) -> np.ndarray:
        """Box actions `(..., n, A)` clipped to each agent's bounds, as they reach the env (a Gaussian's sample is
        not bounded); Discrete ones as they are."""
        return actions if self.discrete else np.clip(actions, self.low, self.high)

    @classmethod
    def of(cls, env: Any) -> EnvLayout:
        """Read a wrapped env's spaces (it is reset once, to find whether it has a state and its size)."""
        agents = tuple(env.possible_agents)
        obs_sizes: list[int] = []
        obs_spaces: list[spaces.Space] = []
        act_spaces: list[spaces.Space] = []
        kinds: list[bool] = []
        sizes: list[int] = []
        lows: list[np.ndarray] = []
        highs: list[np.ndarray] = []
        for a in agents:
            obs_space = env.observation_space(a)["observation"]
            act_space = env.action_space(a)["action"]
            if not obs_space.is_np_flattenable:
                raise bad_value(
                    f"observation_space({a!r})", obs_space,
                    "learning needs one gymnasium can flatten to a vector (Box, Discrete, MultiDiscrete, "
                    "MultiBinary, or a Dict or Tuple of them)",
                )  # fmt: skip
            obs_sizes.append(spaces.flatdim(obs_space))
            obs_spaces.append(obs_space)
            act_spaces.append(act_space)
            if isinstance(act_space, (spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)):
                count = int(np.prod(_components(act_space), dtype=np.float64))  # float: no overflow before the check
                if count > MAX_JOINT_ACTIONS:
                    raise bad_value(
                        f"action_space({a!r})", act_space,
                        f"learning acts on its {count} combinations as one categorical, {MAX_JOINT_ACTIONS} at most",
                    )  # fmt: skip
                kinds.append(True)
                sizes.append(count)
                lows.append(np.zeros(0))
                highs.append(np.zeros(0))
            elif isinstance(act_space, spaces.Box):
                kinds.append(False)
                sizes.append(int(np.prod(act_space.shape)))
                lows.append(np.asarray(act_space.low, np.float32).ravel())
                highs.append(np.asarray(act_space.high, np.float32).ravel())
            else:
                raise bad_value(
                    f"action_space({a!r})",
                    act_space,
                    "learning supports Discrete, MultiDiscrete, MultiBinary or Box actions",
                )
        if len(set(kinds)) != 1:  # name an agent of each kind: which of the env's agents is the odd one
            box, other = (agents[kinds.index(kind)] for kind in (False, True))
            raise bad_value(
                f"action_space({box!r})", act_spaces[kinds.index(False)], f"is a Box while action_space({other!r}) is "
                f"{act_spaces[kinds.index(True)]}: learning needs every agent's actions Box, or every agent's "
                "Discrete, MultiDiscrete or MultiBinary",
            )  # fmt: skip
        width = max(sizes)
        low, high = np.zeros((len(agents), width), np.float32), np.zeros((len(agents), width), np.float32)
        for i, (lo, hi) in enumerate(zip(lows, highs, strict=True)):
            low[i, : lo.size], high[i, : hi.size] = lo, hi
        reset_someone_plays(env, 0)
        state = inner_state(env)
        has_state = state is not None
        state_size = int(state.size) if state is not None else len(agents) * max(obs_sizes)
        fixed = np.array([a in (env.fixed_actions or {}) for a in agents], dtype=bool)
        return cls(
            agents, tuple(obs_sizes), int(env.slot_senders.shape[1]), int(env.bits), int(env.delay), kinds[0],
            tuple(sizes), low, high, state_size, has_state, fixed, np.asarray(env.recipients, dtype=bool),
            tuple(obs_spaces), tuple(act_spaces),
        )  # fmt: skip


def reset_someone_plays(env: Any, seed: int) -> dict[Any, Any]:
    """The observations of `env.reset(seed=seed)`, or one line if it lists no agent: stepped with no one to act, the
    episode ended at once, and a run of such episodes learned nothing and reported a return of 0."""
    obs, _ = env.reset(seed=seed)
    if not env.agents:
        raise bad_value(
            "env.agents", [], f"after reset(seed={seed}): no agent would act in the episode; a ParallelEnv's reset "
            "lists the agents that play first",
        )  # fmt: skip
    return obs


def inner_state(env: Any) -> np.ndarray | None:
    """The env's global state flattened, or None where it has none: PettingZoo's rule is that an env with a
    state has a `state_space` (BitChannel keeps the inner one). Without it `state()` may be PettingZoo's default,
    which raises, or break otherwise (classic envs keep a dict named `state`, so theirs raises TypeError). A state
    that is not an array of numbers (a dict, None) is one line."""
    if not hasattr(env, "state_space"):
        return None
    try:
        state = env.state()
    except (AttributeError, NotImplementedError):
        return None
    try:
        values = np.asarray(state)
    except ValueError:  # a ragged list
        values = np.asarray(None)
    if values.dtype.kind not in "biuf":  # a dict, a string, None (which float32 made NaN)
        raise bad_value("state()", type(state).__name__, "must be an array of numbers (the critic reads it flattened)")
    return values.astype(np.float32).ravel()


class VecObservation(NamedTuple):
    """What the B copies show at one step (rows of ended copies are zeros)."""

    obs: np.ndarray  # (B, n, D) float32
    received: np.ndarray  # (B, n, slots, K) uint8
    state: np.ndarray  # (B, Ds) float32
    alive: np.ndarray  # (B, n) bool


class VecStep(NamedTuple):
    """The outcome of one step of the B copies."""

    next: VecObservation
    rewards: np.ndarray  # (B, n) float32, 0 for absent agents
    dropped: np.ndarray  # (B, n) bool: the message the agent sent this step was lost
    ended: np.ndarray  # (B,) bool: the copy's episode ended with this step


@dataclass(frozen=True)
class WrappedEnvMaker:
    """Makes one copy of a PettingZoo env (by its spec `"package.module:factory"` and keyword arguments) wrapped
    in `BitChannel` with these channel options. Plain data, so it pickles: a worker process builds its copies
    with it (a closure would not cross the process boundary)."""

    env: str
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    bits: int = 7
    delay: int = 1
    flip_prob: float = 0.0
    drop_prob: float = 0.0
    topology: str | list[tuple[str, str]] = "all"
    fixed_actions: dict[str, Any] | None = None

    def __call__(self) -> ParallelEnv:
        inner = make_parallel_env(self.env, self.env_kwargs)
        # JSON (--topology, --fixed-actions, config.json) writes every agent name as a string: "0" is agent 0
        named = {str(a): a for a in possible_agents_of(inner)}
        topology = self.topology
        if not isinstance(topology, str):
            topology = [(named.get(s, s), named.get(r, r)) for s, r in topology]
        fixed = None if self.fixed_actions is None else {named.get(a, a): v for a, v in self.fixed_actions.items()}
        return BitChannel(
            inner, bits=self.bits, delay=self.delay, flip_prob=self.flip_prob, drop_prob=self.drop_prob,
            topology=topology, fixed_actions=fixed,
        )  # fmt: skip


class VecEnv:
    """B wrapped envs made by `make()`; `reset(seeds)` then `step(...)` until every copy has ended; `close()`
    (or `with`) closes them."""

    def __init__(self, make: Callable[[], ParallelEnv], num_envs: int) -> None:
        self.envs = [make() for _ in range(num_envs)]
        self.layout = EnvLayout.of(self.envs[0])
        self.num_envs = num_envs
        self.running = np.zeros(num_envs, dtype=bool)

    def _empty(self) -> VecObservation:
        L, B = self.layout, self.num_envs
        return VecObservation(
            np.zeros((B, L.n, L.obs_dim), np.float32),
            np.zeros((B, L.n, L.slots, L.bits), np.uint8),
            np.zeros((B, L.state_size), np.float32),
            np.zeros((B, L.n), bool),
        )

    def _write(self, out: VecObservation, b: int, obs: dict[str, Any]) -> None:
        """Row b of `out` from one copy's observation dict (the only per-agent loop: dicts to arrays)."""
        env, L = self.envs[b], self.layout
        live = set(env.agents)
        if not live <= obs.keys():  # it would act on zeros and be counted absent: learned from, and rewarded, never
            missing = next(a for a in env.agents if a not in obs)
            raise bad_value(
                "observations", sorted(map(str, obs)), f"the env gave none for {missing!r}, which is in env.agents; "
                "a ParallelEnv observes every agent it lists",
            )  # fmt: skip
        agent_rows(L, obs, live, out.obs[b], out.received[b], out.alive[b])
        state = inner_state(env) if L.has_state else None
        if state is not None and state.size != L.state_size:  # else numpy's "could not broadcast", in a traceback
            raise bad_value(
                "state() size", state.size, f"must keep the size it had at reset ({L.state_size} numbers once "
                "flattened, what the critic reads)",
            )  # fmt: skip
        out.state[b] = state if state is not None else out.obs[b].ravel()

    def reset(self, seeds: Sequence[int] | np.ndarray) -> VecObservation:
        out = self._empty()
        for b, env in enumerate(self.envs):
            self._write(out, b, reset_someone_plays(env, int(seeds[b])))
        check_finite(self.layout, out.obs, out.state if self.layout.has_state else None)
        self.running[:] = True
        return out

    def step(self, actions: np.ndarray, messages: np.ndarray) -> VecStep:
        """`actions (B, n)` int (Discrete) or `(B, n, A)` float (Box, clipped to the bounds here),
        `messages (B, n, K)` uint8; entries of absent agents and ended copies are ignored."""
        L = self.layout
        out = self._empty()
        rewards = np.zeros((self.num_envs, L.n), np.float32)
        dropped = np.zeros((self.num_envs, L.n), bool)
        ended = np.zeros(self.num_envs, bool)
        actions = L.clip(actions)
        for b in np.flatnonzero(self.running):
            env = self.envs[b]
            acting = [(i, a) for i, a in enumerate(L.agents) if a in env.agents]
            joint = joint_action(L, actions[b], messages[b], acting)
            obs, rew, term, trunc, infos = env.step(joint)
            for i, a in acting:
                rewards[b, i] = agent_reward(rew, a)
                dropped[b, i] = bool(infos.get(a, {}).get("message_dropped", False))
            # over when no listed agent plays on (an env may list every agent, all done, at the end; an agent
            # may join at the step the others finish)
            if all(term.get(a, False) or trunc.get(a, False) for a in env.agents):
                ended[b] = True
                self.running[b] = False
            else:
                self._write(out, int(b), obs)
        check_finite(L, out.obs, out.state if L.has_state else None)
        return VecStep(out, rewards, dropped, ended)

    def close(self) -> None:
        for env in self.envs:
            env.close()

    def __enter__(self) -> VecEnv:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


def agent_rows(
    layout: EnvLayout,
    observations: Mapping[Any, Any],
    live: set[Any] | Sequence[Any],
    obs: np.ndarray,
    received: np.ndarray,
    alive: np.ndarray,
) -> None:
    """One wrapped env's observation dict written into its rows: `obs (n, D)`, `received (n, slots, K)`, `alive
    (n,)`, zeros left for the agents not in `live` (a `VecEnv` copy's, and `bitcomm.EnvController`'s for a loop of
    its user's, so that both show the network the same inputs)."""
    for i, a in enumerate(layout.agents):
        if a in live and a in observations:
            obs[i, : layout.obs_sizes[i]] = flat_row(layout, i, observations[a]["observation"])
            received[i] = observations[a]["messages"]
            alive[i] = True


def flat_row(layout: EnvLayout, i: int, observation: Any) -> np.ndarray:
    """Agent i's inner observation flattened (`flat_observation`), or one line naming it if it does not fit the
    agent's space: a value gymnasium cannot flatten, one of another size (which would be cut, broadcast or
    refused by numpy without a word about the env), or one whose values would be read as others (`outside_space`)."""
    space, where = layout.obs_spaces[i], f"observations[{layout.agents[i]!r}]['observation']"
    try:
        flat = flat_observation(space, observation)
        outside = outside_space(space, observation)
    except (TypeError, ValueError, IndexError, KeyError, AssertionError) as err:
        raise bad_value(where, type(observation).__name__, f"does not fit {space} ({one_line(err)})") from None
    if flat.size != layout.obs_sizes[i]:
        raise bad_value(
            f"{where} shape", np.shape(observation),
            f"must fit {space} ({layout.obs_sizes[i]} numbers once flattened, not {flat.size})",
        )  # fmt: skip
    if outside is not None:
        raise bad_value(where, type(observation).__name__, f"does not fit {space} ({outside})")
    return flat


def outside_space(space: spaces.Space, observation: Any) -> str | None:
    """What in an observation gymnasium flattened it would read as another value, or None: its one-hot of a
    Discrete indexes from the end for a value below `start` (-1 of Discrete(5) reads as 4), a MultiBinary entry
    passes as it is (a 2 is not a bit), and an array of the right size in another shape is read in the space's
    order (a (5, 4, 3) image for a (4, 5, 3) space: its pixels scrambled; a Discrete(5)'s value given as its one-hot
    [0, 0, 1, 0, 0] set the one-hot's entries 0 and 1), so the network would read other values without a word. Axes
    of length 1 are left out of the comparison: they change no number's place."""
    if isinstance(space, spaces.Dict):
        return next((w for key, part in space.spaces.items() if (w := outside_space(part, observation[key]))), None)
    if isinstance(space, spaces.Tuple):
        return next(
            (w for part, x in zip(space.spaces, observation, strict=True) if (w := outside_space(part, x))), None
        )
    if not isinstance(space, (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)):
        return None
    x = np.asarray(observation)
    if _unit_free(x.shape) != _unit_free(space.shape or ()):  # a Discrete's is (): one number, not its one-hot
        return f"shape {x.shape} is not the space's {space.shape}: which of its numbers is which cannot be told"
    if isinstance(space, spaces.Discrete):
        low, high = space.start, space.start + space.n
    elif isinstance(space, spaces.MultiDiscrete):
        low, high, x = space.start, space.start + space.nvec, x.reshape(space.shape)
    elif isinstance(space, spaces.MultiBinary):
        low, high = 0, 2
    else:
        return None
    bad = (x < low) | (x >= high) | (x != np.floor(x))
    return f"{x[bad].flat[0].item()!r} is not a value of {space}" if bad.any() else None


def _unit_free(shape: tuple[int, ...]) -> tuple[int, ...]:
    """A shape without its axes of length 1 (which change no number's place in C order)."""
    return tuple(k for k in shape if k != 1)


def check_finite(layout: EnvLayout, obs: np.ndarray, state: np.ndarray | None = None) -> None:
    """One line for a NaN or infinite observation `(..., n, D)` (or critic state `(..., Ds)` read from the env's
    `state()`), naming the agent: the network would turn it into NaN probabilities and stop in a traceback
    from torch's sampler, or as "training diverged", blaming the learning rate for the env's value."""
    if not np.isfinite(obs).all():
        where = np.argwhere(~np.isfinite(obs))[0]
        agent, value = layout.agents[int(where[-2])], obs[tuple(where)]
        raise bad_value(
            f"observations[{agent!r}]['observation']", value.item(), "the env's observations must be finite numbers "
            "(as float32; the network cannot read NaN or infinity)",
        )  # fmt: skip
    if state is not None and not np.isfinite(state).all():
        value = state[~np.isfinite(state)][0]
        raise bad_value("state()", value.item(), "the env's state must be finite numbers (as float32)")


def joint_action(
    layout: EnvLayout, actions: np.ndarray, messages: np.ndarray, acting: Sequence[tuple[int, Any]]
) -> dict[Any, dict[str, Any]]:
    """The dict `BitChannel.step` takes, for the `(row, agent)` pairs of `acting`, from one env's rows of the
    learner's arrays: `actions (n,)` or `(n, A)` (clipped: `EnvLayout.clip`), `messages (n, K)`."""
    return {a: {"action": inner_action(layout.action_spaces[i], actions[i]), "message": messages[i]} for i, a in acting}


def agent_reward(rewards: Mapping[Any, Any], agent: Any) -> float:
    """The reward of an agent that acted this step, from the env's dict, or one line naming it: PettingZoo's API
    test warns of a live agent given no reward, and nothing documents a missing one as 0, so it is the env's bug,
    not a reward of 0 to learn from."""
    if agent not in rewards:  # `in`: not a defaultdict's made-up 0 (aec_to_parallel returns one)
        raise bad_value(
            "rewards", sorted(map(str, rewards)), f"the env gave none for {agent!r}, which acted this step; a "
            "ParallelEnv rewards every agent that acts (0.0 for no reward)",
        )  # fmt: skip
    return finite_reward(rewards[agent], agent)


def finite_reward(value: Any, agent: Any) -> float:
    """An agent's reward as a float, or one line naming it: a NaN or infinite reward (or one that is not a
    number) would otherwise reach the learner and stop the run as "training diverged", blaming the learning
    rate for the env's value; an array (even of one number: numpy will not make it a float) is named by its
    shape."""
    try:
        shape = np.shape(value)
    except ValueError:  # a ragged list: not a number either
        shape = ()
    if shape != ():
        raise bad_value(
            f"rewards[{agent!r}] shape", shape, "the env's rewards must be scalars, one number per agent (not arrays)"
        )
    try:
        reward = float(value)
    except (TypeError, ValueError):
        reward = math.nan
    if not math.isfinite(reward):
        raise bad_value(f"rewards[{agent!r}]", value, "the env's rewards must be finite numbers")
    return reward


def flat_observation(space: spaces.Space, observation: Any) -> np.ndarray:
    """An inner observation as the flat float32 vector the networks read (a Box's values as they are)."""
    if isinstance(space, spaces.Box):
        return np.asarray(observation, np.float32).ravel()
    return np.asarray(spaces.flatten(space, observation), np.float32)


def _components(space: spaces.Space) -> list[int]:
    """The sizes of a discrete action space's parts: one for Discrete, one per entry of MultiDiscrete, MultiBinary."""
    if isinstance(space, spaces.Discrete):
        return [int(space.n)]
    if isinstance(space, spaces.MultiDiscrete):
        return [int(k) for k in space.nvec.ravel()]
    return [2] * spaces.flatdim(space)


def inner_action(space: spaces.Space, action: np.ndarray) -> Any:
    """The inner env's action from the learner's: a Discrete index from 0 shifted by the space's `start`; a
    MultiDiscrete or MultiBinary one unravelled from the index of its combination (C order: the last entry varies
    fastest), shaped, shifted and typed as the space; a flat Box vector (padded to the widest agent's) cut to the
    space's size, shaped and typed as it (an integer Box's rounded to the nearest), and clipped to its own bounds in its
    dtype (the learner clips in float32, whose nearest bound can lie just outside a float64 one: 0.1 becomes
    0.10000000149)."""
    if isinstance(space, spaces.Discrete):
        return int(action) + int(space.start)
    if isinstance(space, (spaces.MultiDiscrete, spaces.MultiBinary)):
        parts = np.array(np.unravel_index(int(action), _components(space))).reshape(space.shape)
        if isinstance(space, spaces.MultiDiscrete):
            parts = parts + space.start
        return parts.astype(space.dtype)
    if not isinstance(space, spaces.Box):  # EnvLayout.of refuses any other action space
        raise TypeError(f"no learner action for {space}")
    box = np.asarray(action[: spaces.flatdim(space)], np.float32).reshape(space.shape)
    if np.issubdtype(space.dtype, np.integer):  # the nearest integer: a cast cut 2.7 to 2 and -0.6 to 0
        box = np.rint(box)
    box = box.astype(space.dtype, copy=False)
    return np.asarray(
        np.clip(box, space.low, space.high), dtype=space.dtype
    )  # asarray: a shape () Box's stays an array
