"""
# Goal Exchange

| Import             | `from bitcomm.envs import goal_exchange_v0`                        |
|--------------------|--------------------------------------------------------------------|
| Parallel API       | Yes (`goal_exchange_v0.parallel_env(...)`); AEC via `env(...)`     |
| Agents             | `agents = ['agent_0', ..., 'agent_{n-1}']`, n = `n_agents` (2)     |
| Action Shape       | `Dict(move=Discrete(5), message=MultiBinary(K))`                   |
| Observation Shape  | `Dict(planes=(2, size, size), received=(slots, K))`, uint8 in {0,1}|
| State Shape        | `(2 * n, size, size)` uint8 in {0, 1}                              |

The cooperative goal-exchange task of "Simultaneous Policy and Discrete Communication Learning for
Multi-Agent Cooperation" (section IV), with the paper's defaults: n agents share a `size x size`
grid; each must reach its own goal cell, but only another agent sees that goal. The only way to
learn it is a message of K bits over a channel that delays, and may flip or drop, what is sent.

This is a thin view over `bitcomm.envs.VecGoalExchange` with one episode: the dynamics exist once,
in the vectorized core (SPEC sections 1 and 2).

### Arguments

```python
goal_exchange_v0.parallel_env(size=10, n_agents=2, max_steps=256, observes=None, act_fail_prob=0.0,
                              act_delay=0, bits=7, recipients=None, delay=1, flip_prob=0.0,
                              drop_prob=0.0, render_mode=None)
```

- `size`: the grid is `size x size` (>= 2). `n_agents`: >= 2; agents may share a cell.
- `max_steps`: the episode is truncated after this many steps.
- `observes`: `observes[i]` is the agent whose goal agent i sees (never i); default the ring `(i + 1) % n`.
- `act_fail_prob`, `act_delay`: actuation noise (not in the paper, default off): a move is not executed
  with this probability; moves take effect `act_delay` steps after they are chosen.
- `bits`: message size K. `recipients[j]`: the agents that receive agent j's message; default the agent
  whose goal j sees.
- `delay`: a message sent at step t is received at step t + delay (>= 1); zeros before that.
- `flip_prob`: each bit flips in transit with this probability. `drop_prob`: a message is lost with
  this probability and every recipient reads zeros.
- `render_mode`: None or `"ansi"` (a text grid).

A numpy integer or float is taken wherever a Python one is (`size=np.int64(4)`). A bad value raises
`bitcomm.errors.ConfigError`, whose one-line message names the parameter.

### Observation Space

`planes[0]` is a one-hot plane of the agent's own position, `planes[1]` a one-hot plane of the goal of
the agent it observes; it never sees its own goal. Planes are indexed `[row, column]`.
`received[s]` is the K-bit message heard in slot s: one slot per sender the agent hears, ordered by
sender index (`slots` = the most senders any agent hears; 1 by default); zeros when nothing has
arrived, the message was dropped, or the slot is unused. Policies in the paper are reactive.

### Action Space

`move`: 0 stay, 1 up (row - 1), 2 down (row + 1), 3 left (column - 1), 4 right (column + 1); a move
off the grid leaves the agent in place and counts as invalid. `message`: the K bits sent this step.
`step` takes one action per live agent, each a dict of exactly these two keys: `move` a Python or numpy
integer (or a 0-d integer array) in [0, 5), never a bool or a float; `message` K values in {0, 1}; what
`action_space(agent).sample()` gives is one. Anything else, or an action for an agent not in `agents`,
raises `ConfigError` with one line naming it, before the episode moves; a live agent without an action
raises `KeyError`.

### Rewards

Computed after all agents moved: 0 for an agent that ends the step on its goal; otherwise -0.3,
+0.2 if its Manhattan distance to its goal shrank, -0.1 if it stayed or moved invalidly (a move the
actuation noise cancelled counts as staying). `rewards[agent]` is the agent's own reward; the team
reward (their sum, on which the paper trains every agent) is in `infos[agent]["team_reward"]`.

### Termination, truncation, infos

Every agent terminates at the first step after which all stand on their goals; all are truncated
after `max_steps`. Then `agents` empties and `reset()` starts a new episode. `infos[agent]` holds
`team_reward` and `dropped` (whether the channel lost the message the agent sent this step).
`state()` gives the critics' full state: every agent's position plane, then every goal plane.
`reset(seed=s)` reseeds the task and the channel noise deterministically.

### Version History

* v0: Initial release (bitcomm 0.1.0).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import logger, spaces
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.core import N_MOVES
from bitcomm.envs.render import render_ansi
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import ConfigError, bad_value, is_integer

AgentID = str
ObsDict = dict[str, np.ndarray]
ActionDict = dict[str, Any]
RENDER_MODES = ("ansi",)
ACTION_KEYS = {"move", "message"}
# observations, rewards, terminations, truncations, infos
StepReturn = tuple[
    dict[AgentID, ObsDict], dict[AgentID, float], dict[AgentID, bool], dict[AgentID, bool], dict[AgentID, dict]
]


class GoalExchangeParallelEnv(ParallelEnv[AgentID, ObsDict, ActionDict]):
    """One episode of the goal-exchange task at a time, as a PettingZoo `ParallelEnv`."""

    metadata = {"name": "goal_exchange_v0", "render_modes": list(RENDER_MODES), "is_parallelizable": True}

    def __init__(self, task: TaskConfig, render_mode: str | None = None) -> None:
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise bad_value("render_mode", render_mode, "must be None or 'ansi'")
        self.task = task
        self.render_mode = render_mode
        n, S, K = task.env.n_agents, task.env.size, task.channel.bits
        self.possible_agents = [f"agent_{i}" for i in range(n)]
        self.agents: list[AgentID] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        # one space object per agent, built once: PettingZoo requires the same object on every call
        self.observation_spaces = {
            a: spaces.Dict(
                planes=spaces.Box(0, 1, (2, S, S), np.uint8),
                received=spaces.Box(0, 1, (task.slots, K), np.uint8),
            )
            for a in self.possible_agents
        }
        self.action_spaces = {
            a: spaces.Dict(move=spaces.Discrete(N_MOVES), message=spaces.MultiBinary(K)) for a in self.possible_agents
        }
        self.state_space = spaces.Box(0, 1, (2 * n, S, S), np.uint8)
        self._vec: VecGoalExchange | None = None

    def observation_space(self, agent: AgentID) -> spaces.Dict:
        return self.observation_spaces[agent]

    def action_space(self, agent: AgentID) -> spaces.Dict:
        return self.action_spaces[agent]

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[AgentID, ObsDict], dict[AgentID, dict]]:
        if seed is not None or self._vec is None:
            # autoreset off: a finished episode keeps its terminal observation until the next reset
            self._vec = VecGoalExchange(self.task, 1, seed=seed, autoreset=False)
        else:
            self._vec.reset()
        self.agents = self.possible_agents[:]
        return self._observations(), {a: {} for a in self.agents}

    def step(self, actions: dict[AgentID, ActionDict]) -> StepReturn:
        if self._vec is None or not self.agents:
            raise RuntimeError("the episode is over: call reset() before step()")
        if not isinstance(actions, Mapping):
            raise bad_value("actions", actions, f"must be a dict from live agent to action (live: {self.agents})")
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            raise bad_value("agent", unknown[0], f"actions are for live agents only: {self.agents}")
        n = self.task.env.n_agents
        moves = np.zeros((1, n), dtype=np.int64)
        bits = np.zeros((1, n, self.task.channel.bits), dtype=np.uint8)
        for agent in self.agents:
            if agent not in actions:
                raise KeyError(f"no action for live agent {agent!r}")
            i = self._index[agent]
            moves[0, i], bits[0, i] = self._action(agent, actions[agent])

        result, dropped = self._vec.step(moves, bits)
        team = float(result.team_reward[0])
        terminated, truncated = bool(result.terminated[0]), bool(result.truncated[0])
        observations = self._observations()
        rewards = {a: float(result.rewards[0, self._index[a]]) for a in self.agents}
        terminations = dict.fromkeys(self.agents, terminated)
        truncations = dict.fromkeys(self.agents, truncated)
        infos = {a: {"team_reward": team, "dropped": bool(dropped[0, self._index[a]])} for a in self.agents}
        if terminated or truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def _action(self, agent: AgentID, action: Any) -> tuple[int, np.ndarray]:
        """`agent`'s move and K bits, or one line naming what is wrong. An action is what
        `action_space(agent).sample()` gives: a dict of exactly `move`, an integer in [0, 5) (a Python or numpy
        integer, or a 0-d integer array; not a bool, not a float), and `message`, K bits in {0, 1}."""
        name = f"actions[{agent!r}]"
        if not isinstance(action, Mapping):
            raise bad_value(name, action, "must be a dict with the keys 'move' and 'message'")
        if set(action) != ACTION_KEYS:
            keys = ", ".join(sorted(map(repr, action)))
            raise ConfigError(
                f"invalid {name}: has the keys {keys or 'none'}; an action has exactly 'move' and 'message'"
            )
        move, K = action["move"], self.task.channel.bits
        if isinstance(move, np.ndarray) and move.shape == ():
            move = move[()]  # a 0-d array: its scalar
        if not is_integer(move) or not 0 <= move < N_MOVES:
            raise bad_value(f"{name}['move']", action["move"], f"must be an integer in [0, {N_MOVES})")
        message = np.asarray(action["message"])
        if message.shape != (K,) or not np.isin(message, (0, 1)).all():
            raise bad_value(f"{name}['message']", action["message"], f"must be {K} bits in {{0, 1}}")
        return int(move), message

    def _observations(self) -> dict[AgentID, ObsDict]:
        assert self._vec is not None
        obs = self._vec.observe()
        return {
            a: {"planes": obs.planes[0, i].copy(), "received": obs.received[0, i].copy()}
            for a, i in self._index.items()
            if a in self.agents
        }

    def state(self) -> np.ndarray:
        """Full state for critics: `(2n, size, size)`, every position plane then every goal plane."""
        if self._vec is None:
            raise RuntimeError("call reset() first")
        return self._vec.core.state[0].copy()

    def render(self) -> str | None:
        if self.render_mode is None:
            logger.warn("render() called without a render_mode; use render_mode='ansi'")
            return None
        if self._vec is None:
            raise RuntimeError("call reset() first")
        core = self._vec.core
        return render_ansi(core.pos[0], core.goal[0], self.task.env.size)


def parallel_env(
    size: int = 10,
    n_agents: int = 2,
    max_steps: int = 256,
    observes: tuple[int, ...] | list[int] | None = None,
    act_fail_prob: float = 0.0,
    act_delay: int = 0,
    bits: int = 7,
    recipients: tuple[tuple[int, ...], ...] | list[list[int]] | None = None,
    delay: int = 1,
    flip_prob: float = 0.0,
    drop_prob: float = 0.0,
    render_mode: str | None = None,
) -> GoalExchangeParallelEnv:
    """The task as a PettingZoo `ParallelEnv`; every parameter of SPEC sections 1 and 2 is a keyword. A numpy
    number is taken wherever a Python one is (`size=np.int64(4)`, `flip_prob=np.float32(0.1)`); a bool is not."""
    task = TaskConfig(
        EnvConfig(
            size=size,
            n_agents=n_agents,
            max_steps=max_steps,
            observes=None if observes is None else tuple(observes),
            act_fail_prob=act_fail_prob,
            act_delay=act_delay,
        ),
        ChannelConfig(
            bits=bits,
            recipients=None if recipients is None else tuple(tuple(r) for r in recipients),
            delay=delay,
            flip_prob=flip_prob,
            drop_prob=drop_prob,
        ),
    )
    return GoalExchangeParallelEnv(task, render_mode=render_mode)


def env(**kwargs: Any) -> AECEnv:
    """The same task through PettingZoo's AEC API (agents act in turn; the step resolves once all have)."""
    return parallel_to_aec(parallel_env(**kwargs))
