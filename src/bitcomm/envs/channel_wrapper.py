"""
# BitChannel: bitcomm's K-bit channel on any PettingZoo `ParallelEnv` (SPEC section 8)

| Import             | `from bitcomm.envs.channel_wrapper import BitChannel` (or `bitcomm.BitChannel`)  |
|--------------------|----------------------------------------------------------------------------------|
| Wraps              | any `ParallelEnv` whose spaces are gymnasium spaces (the learner: see vector.py)  |
| Action Shape       | `Dict(action=<inner action space>, message=MultiBinary(K))`                      |
| Observation Shape  | `Dict(observation=<inner space>, messages=MultiBinary((slots, K)))`               |
| State              | the inner `state()` and `state_space`, unchanged, when the inner env has them     |

Each agent's action gains K message bits; each observation gains the bits received from the
senders the topology gives it. The channel is `bitcomm.channel.Channel`, the grid's own: bits sent
at step t are in the observation returned by step t + delay - 1 (acted on at step t + delay), zeros
before the first delivery and after `reset()`; each bit flips in transit with `flip_prob`, each
message is dropped (every recipient reads zeros) with `drop_prob`. Full description and an
example: docs/channel_wrapper.md.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from bitcomm.channel.core import Channel
from bitcomm.channel.topology import Topology, recipients_of
from bitcomm.config import ChannelConfig, Integer, slot_table
from bitcomm.errors import bad_value, one_line

AgentID = str
StepReturn = tuple[
    dict[AgentID, dict[str, np.ndarray]],
    dict[AgentID, float],
    dict[AgentID, bool],
    dict[AgentID, bool],
    dict[AgentID, dict[str, Any]],
]
RESET_PARTS = ("observations", "infos")
"""What a ParallelEnv's `reset` returns, a dict keyed by agent each."""
STEP_PARTS = ("observations", "rewards", "terminations", "truncations", "infos")
"""What a ParallelEnv's `step` returns, a dict keyed by agent each."""
SEED_SALT = 0xB17
"""Mixed into `reset(seed=s)` for the channel's noise, so it never shares a stream with the inner env."""


def channel_seed(seed: int) -> np.random.SeedSequence:
    """The channel noise's seed for an episode reset with `seed` (the inner env gets `seed` itself)."""
    return np.random.SeedSequence([seed, SEED_SALT])


def _check_seed(seed: object) -> None:
    """One error line unless `seed` is None or an integer >= 0 (the constructor's and `reset`'s)."""
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
        raise bad_value("seed", seed, "must be None or an integer >= 0")


class BitChannel(ParallelEnv[AgentID, dict[str, np.ndarray], dict[str, Any]]):
    """A PettingZoo `ParallelEnv` whose agents also talk through a K-bit noisy, delayed channel.

    Spaces, for each agent `a` of `possible_agents`:

    - `observation_space(a) = Dict(observation=<inner space>, messages=MultiBinary((slots, K)))`: row s of
      `messages` holds the bits from the s-th sender that `a` hears, senders in `possible_agents` order;
      rows beyond the senders `a` hears stay zero; `slots` is the most senders any agent hears (>= 1).
    - `action_space(a) = Dict(action=<inner space>, message=MultiBinary(K))`.

    The inner spaces are carried as they are, whatever their type (Box, Discrete, MultiDiscrete, Dict...);
    `bitcomm train --env` learns on those `bitcomm.envs.vector.EnvLayout` accepts.

    `step(actions)` takes actions for the live agents (`agents`); actions for agents that have left
    are ignored, and such agents send zeros (their slot reads zeros, whatever the noise). The inner env
    must drop a finished agent from its `agents` (PettingZoo's rule): one line otherwise. Rewards,
    terminations, truncations and infos are the inner env's; `infos[a]["message_dropped"]` says
    whether the message `a` sent this step was dropped.

    Attributes for learners: `inner` (the wrapped env), `possible_agents`, `agents`, `bits`, `delay`,
    `channel_config` (`ChannelConfig`), `recipients` (`(n, n)` bool, `[j, x]`: x hears j, in
    `possible_agents` order), `slot_senders` (`(n, slots)` int, -1 padding; `bitcomm.config.slot_table`),
    `fixed_actions` (agent -> the inner action it always takes; a learner ignores those action heads),
    `metadata` (the inner one, name suffixed `_bitchannel`), and `state_space` when the inner env has one.
    """

    def __init__(
        self,
        env: ParallelEnv,
        bits: int = 7,
        delay: int = 1,
        flip_prob: float = 0.0,
        drop_prob: float = 0.0,
        topology: Topology = "all",
        seed: Integer | None = None,
        fixed_actions: Mapping[str, Any] | None = None,
    ) -> None:
        if not isinstance(env, ParallelEnv):
            raise bad_value(
                "env",
                type(env).__name__,
                "must be a PettingZoo ParallelEnv (pettingzoo.utils.aec_to_parallel converts an AEC env)",
            )
        _check_seed(seed)
        _check_reset_takes_seed(env)
        self.inner = env
        self.possible_agents: list[AgentID] = possible_agents_of(env)
        self.agents: list[AgentID] = []
        n = len(self.possible_agents)
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self.recipients = recipients_of(self.possible_agents, topology)
        self.slot_senders = slot_table(self.recipients)
        # validates bits, delay and the probabilities, one line each
        self.channel_config = ChannelConfig(
            bits=bits,
            recipients=tuple(tuple(int(x) for x in np.flatnonzero(row)) for row in self.recipients),
            delay=delay,
            flip_prob=flip_prob,
            drop_prob=drop_prob,
        )
        self.bits, self.delay = self.channel_config.bits, self.channel_config.delay
        slots = self.slot_senders.shape[1]
        inner_obs = {a: _inner_space(env, a, "observation") for a in self.possible_agents}
        inner_act = {a: _inner_space(env, a, "action") for a in self.possible_agents}
        self.fixed_actions = _check_fixed(fixed_actions, inner_act)
        # one space object per agent, built once: PettingZoo requires the same object on every call
        self.observation_spaces = {
            a: spaces.Dict(observation=inner_obs[a], messages=spaces.MultiBinary((slots, self.bits)))
            for a in self.possible_agents
        }
        self.action_spaces = {
            a: spaces.Dict(action=inner_act[a], message=spaces.MultiBinary(self.bits)) for a in self.possible_agents
        }
        if hasattr(env, "state_space"):
            self.state_space = env.state_space
        self.metadata = dict(getattr(env, "metadata", {}))
        self.metadata["name"] = f"{self.metadata.get('name', type(env).__name__)}_bitchannel"
        self.render_mode = getattr(env, "render_mode", None)
        first = None if seed is None else int(seed)  # a numpy integer as the int it is, which gymnasium's seeding takes
        self._first_seed = first  # used by the first reset() if it is given no seed
        self._channel = self._new_channel(None if first is None else channel_seed(first))
        # who was live when each message in flight was sent: the same delay queue, noise-free, one bit
        self._alive = Channel(ChannelConfig(bits=1, delay=self.delay), self.slot_senders, num_envs=1)
        self._n = n

    def _new_channel(self, seed: np.random.SeedSequence | None) -> Channel:
        return Channel(self.channel_config, self.slot_senders, num_envs=1, seed=seed)

    def observation_space(self, agent: AgentID) -> spaces.Dict:
        return self.observation_spaces[agent]

    def action_space(self, agent: AgentID) -> spaces.Dict:
        return self.action_spaces[agent]

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[AgentID, dict[str, np.ndarray]], dict[AgentID, dict[str, Any]]]:
        """Reset the inner env and empty the channel. `seed` seeds both (the channel from
        `SeedSequence([seed, 0xB17])`); without one, the first reset uses the constructor's `seed` and
        later ones continue the streams."""
        _check_seed(seed)  # else numpy's "expected non-negative integer", naming no seed
        seed = self._first_seed if seed is None else int(seed)  # a numpy integer, which gymnasium's seeding refuses
        self._first_seed = None
        if seed is not None:
            self._channel = self._new_channel(channel_seed(seed))
        else:
            self._channel.reset()
        self._alive.reset()
        # options only when given: an env whose reset() takes no options is wrapped as it is
        extra = {} if options is None else {"options": options}
        observations, infos = _parts(self.inner.reset(seed=seed, **extra), "reset()", RESET_PARTS)
        self.agents = _listed(self.inner, self._index)
        empty = np.zeros((self._n,) + self.slot_senders.shape[1:] + (self.bits,), dtype=np.int8)
        return self._augment(observations, empty), infos

    def step(self, actions: dict[AgentID, dict[str, Any]]) -> StepReturn:
        """One step of the inner env with the live agents' inner actions, then one step of the channel."""
        unknown = actions.keys() - self._index.keys()
        if unknown:
            raise KeyError(f"actions for unknown agents {sorted(unknown)}; agents are {self.possible_agents}")
        live = list(self.agents)  # actions of agents that have left are ignored
        for agent in live:
            if agent not in actions:
                raise KeyError(f"no action for live agent {agent!r}")
            act = actions[agent]
            if not isinstance(act, Mapping) or not {"action", "message"} <= act.keys():
                raise ValueError(
                    f"{agent}: action must be {{'action': <inner action>, 'message': {self.bits} bits}}, got {act!r}"
                )
        inner_actions = {a: self.fixed_actions.get(a, actions[a]["action"]) for a in live}
        rows = [self._index[a] for a in live]
        sent = np.zeros((1, self._n, self.bits), dtype=np.uint8)
        sent[0, rows] = self._messages([actions[a]["message"] for a in live], live)
        alive = np.zeros((1, self._n, 1), dtype=np.uint8)
        alive[0, rows] = 1
        observations, rewards, terminations, truncations, infos = _parts(
            self.inner.step(inner_actions), "step()", STEP_PARTS
        )
        dropped = self._channel.transmit(sent)[0]
        self._alive.transmit(alive)
        received = (self._channel.received()[0] * self._alive.received()[0]).astype(np.int8)
        infos = {a: dict(info) for a, info in infos.items()}
        for agent, i in zip(live, rows, strict=True):
            infos.setdefault(agent, {})["message_dropped"] = bool(dropped[i])
        self.agents = _live_after_step(self.inner, self._index, terminations, truncations)
        return self._augment(observations, received), rewards, terminations, truncations, infos

    def _messages(self, messages: list[Any], live: list[AgentID]) -> np.ndarray:
        """The live agents' messages as one `(len(live), K)` array, checked at once: K bits in {0, 1} each."""
        shape = (len(live), self.bits)
        try:
            bits = np.asarray(messages) if messages else np.zeros(shape)
        except ValueError:  # messages of different lengths
            bits = np.zeros((0,))
        if bits.shape == shape and ((bits == 0) | (bits == 1)).all():
            return bits
        for agent, message in zip(live, messages, strict=True):  # name the first bad one
            m = np.asarray(message)
            if m.shape != (self.bits,) or not ((m == 0) | (m == 1)).all():
                raise ValueError(f"{agent}: message must be {self.bits} bits in {{0, 1}}, got {message!r}")
        raise ValueError(f"messages must be {self.bits} bits in {{0, 1}} each, got {messages!r}")

    def _augment(self, observations: dict[AgentID, Any], received: np.ndarray) -> dict[AgentID, dict[str, np.ndarray]]:
        """Each inner observation with the `(slots, K)` bits its agent received this step."""
        return {
            a: {"observation": obs, "messages": received[self._index[a]].copy()}
            for a, obs in observations.items()
            if a in self._index
        }

    def state(self) -> np.ndarray:
        """The inner env's `state()` (messages in flight are not part of it)."""
        return self.inner.state()

    def render(self) -> Any:
        return self.inner.render()

    def close(self) -> None:
        self.inner.close()


def possible_agents_of(env: ParallelEnv) -> list[AgentID]:
    """The env's `possible_agents` as a list, or one line unless it names one or more distinct agents. PettingZoo
    sets it in the env's `__init__`; one that sets it only in `reset` (or never) stopped in an AttributeError."""
    agents = getattr(env, "possible_agents", None)
    if agents is None:
        raise bad_value(
            "possible_agents", None, f"{type(env).__name__} has none before reset; a PettingZoo ParallelEnv names "
            "every agent that may play in possible_agents when it is made (in __init__)",
        )  # fmt: skip
    try:
        listed = list(agents)
    except TypeError:
        listed = []
    if not listed or len(set(listed)) != len(listed):
        raise bad_value("possible_agents", agents, "the env must name one or more distinct agents")
    return listed


def _check_reset_takes_seed(env: ParallelEnv) -> None:
    """One line unless the env's `reset` takes `seed=` (a ParallelEnv's is `reset(seed=None, options=None)`): every
    episode is seeded through it, and one without it failed at the first reset with a TypeError from inside the
    wrapper. A `reset` whose signature cannot be read is let through."""
    try:
        params = inspect.signature(env.reset).parameters
    except (TypeError, ValueError):
        return
    if "seed" not in params and not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        raise bad_value(
            "env.reset", f"reset({', '.join(params)})", "must take seed=, as a PettingZoo ParallelEnv's "
            "reset(seed=None, options=None) does: every episode is seeded through it",
        )  # fmt: skip


def _parts(returned: Any, call: str, names: tuple[str, ...]) -> tuple[Any, ...]:
    """What the inner env's `reset()` or `step()` returned, as its parts, each a dict keyed by agent, or one line
    naming what came instead: an env written for an older API (reset's observations alone, step's four values
    with one `dones`) or a None for a dict stopped in an unpacking error or an AttributeError inside the wrapper."""
    if isinstance(returned, (tuple, list)):
        if len(returned) == len(names) and all(isinstance(part, Mapping) for part in returned):
            return tuple(returned)
        what = f"{type(returned).__name__}({', '.join(type(part).__name__ for part in returned)})"
    else:
        what = type(returned).__name__
    raise bad_value(
        f"env.{call}", what, f"a PettingZoo ParallelEnv's {call.rstrip('()')} returns ({', '.join(names)}), a dict "
        "keyed by agent each (an env written for an older API must be updated)",
    )  # fmt: skip


def _listed(env: ParallelEnv, known: Mapping[AgentID, int]) -> list[AgentID]:
    """The inner env's `agents`, or one line if one of them is not in its `possible_agents` (PettingZoo's
    `parallel_api_test` checks it): the wrapper has no slot, topology row or spaces for it, so it would be asked
    for an action no one can give, and its observation dropped."""
    agents = list(env.agents)
    stranger = next((a for a in agents if a not in known), None)
    if stranger is not None:
        raise bad_value(
            "env.agents", agents, f"{stranger!r} is not in possible_agents {list(known)}; a PettingZoo ParallelEnv "
            "lists every agent that may play in possible_agents",
        )  # fmt: skip
    return agents


def _live_after_step(
    env: ParallelEnv, known: Mapping[AgentID, int], terminations: dict[AgentID, bool], truncations: dict[AgentID, bool]
) -> list:
    """The inner env's `agents` after a step, or one line if an agent that just finished is still among them
    while others play on: a ParallelEnv removes an agent once it terminates or truncates (PettingZoo's
    `parallel_api_test` checks it). Kept, it would be asked for actions, and its messages sent, after it left,
    and a learner would count it as present for one more step. An env that lists every agent, all done, at the
    end of the episode is let through: nothing is stepped after it."""
    agents = _listed(env, known)
    done = [a for a in agents if terminations.get(a, False) or truncations.get(a, False)]
    if done and len(done) < len(agents):
        raise bad_value(
            "env.agents", agents, f"{done[0]!r} terminated or truncated at this step but is still listed while "
            "others play on; a PettingZoo ParallelEnv removes an agent from env.agents once it is done",
        )  # fmt: skip
    return agents


def _inner_space(env: ParallelEnv, agent: AgentID, kind: str) -> spaces.Space:
    """The inner env's observation or action space of `agent`, or one error line if it is not a gymnasium space."""
    try:
        space = getattr(env, f"{kind}_space")(agent)
    except Exception as err:  # the env's own lookup (a dict missing the agent, say): one line naming the call
        raise bad_value(
            "env", type(env).__name__, f"its {kind}_space({agent!r}) raised {one_line(err)}; every agent in "
            "possible_agents needs one",
        ) from None  # fmt: skip
    if not isinstance(space, spaces.Space):
        raise bad_value(f"{kind}_space({agent!r})", space, "must be a gymnasium.spaces.Space")
    return space


def _check_fixed(fixed: Mapping[str, Any] | None, action_spaces: dict[AgentID, spaces.Space]) -> dict[AgentID, Any]:
    """`fixed_actions` as a dict of valid inner actions, each checked against its agent's space."""
    if fixed is None:
        return {}
    if not isinstance(fixed, Mapping):
        raise bad_value("fixed_actions", fixed, "must be a mapping from agent name to an inner action")
    out: dict[AgentID, Any] = {}
    for agent, value in fixed.items():
        if agent not in action_spaces:
            raise bad_value("fixed_actions", agent, f"keys must be agents of the env: {list(action_spaces)}")
        space = action_spaces[agent]
        action: Any = value
        if isinstance(space, spaces.Box):
            try:
                with np.errstate(over="ignore"):  # a number beyond the dtype becomes inf, refused below
                    action = np.asarray(value, dtype=space.dtype)
            except (TypeError, ValueError):
                action = None
            if action is not None and not np.isfinite(action).all():  # an unbounded Box contains inf
                raise bad_value(f"fixed_actions[{agent!r}]", value, f"must be a finite action of {space}")
        elif isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            action = int(value)
        if action is None or isinstance(value, bool) or not space.contains(action):
            raise bad_value(f"fixed_actions[{agent!r}]", value, f"must be an action of {space}")
        if isinstance(space, (spaces.MultiDiscrete, spaces.MultiBinary)):  # a JSON list reaches the env as the
            action = np.asarray(action, dtype=space.dtype)  # array of the space's dtype its other actions are
        out[agent] = action
    return out
