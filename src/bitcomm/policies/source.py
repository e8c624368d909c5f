"""Where a command's policy comes from: a reference policy (`--policy oracle|random`), a learned RUN, or a
learned policy exported to ONNX (`--onnx FILE`, run by onnxruntime: see `bitcomm.policies.onnx_policy`).

This module is the one place that turns command-line arguments into an `AgentPolicy` and the task it
runs on, for `bitcomm render`, `analyze`, `deploy` and `sweep`. A learned policy is loaded through
`bitcomm.Controller.load(RUN)` (a run folder or a checkpoint file); until that class exists, RUN is
accepted and answered with one error line.

The task of a learned policy is the one it was trained on (`controller.task`); task flags given on
the command line change it (noise, delays, truncation). Flags left at their defaults do not, which is
why the defaults are marked (`mark_task_defaults`): argparse alone cannot tell "--size 10" from no
flag. Flags that change what the network takes in (size, agents, bits) must match the run.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError, bad_value
from bitcomm.policies.agent_policies import AgentPolicy, ControllerAgent, OracleAgent, RandomAgent
from bitcomm.policies.reference import REFERENCE_POLICIES

LEARNED_UNAVAILABLE = "learned policies need bitcomm.Controller, not available yet"

# task flag (argparse dest) -> (config part, field); the flags of `bitcomm.commands.common.add_task_flags`
TASK_FLAGS: dict[str, tuple[str, str]] = {
    "size": ("env", "size"),
    "agents": ("env", "n_agents"),
    "max_steps": ("env", "max_steps"),
    "observes": ("env", "observes"),
    "act_fail_prob": ("env", "act_fail_prob"),
    "act_delay": ("env", "act_delay"),
    "bits": ("channel", "bits"),
    "recipients": ("channel", "recipients"),
    "delay": ("channel", "delay"),
    "flip_prob": ("channel", "flip_prob"),
    "drop_prob": ("channel", "drop_prob"),
}
POLICY_INPUTS = ("size", "bits")
"""The task flags a trained policy network cannot take other values of. It is shared by every agent and does not know
their number (`bitcomm.Controller`), so a policy trained by 2 may play a ring of 3 where each agent hears as many
senders as in training (`resolve_task` checks that too)."""
CRITIC_INPUTS = (*POLICY_INPUTS, "agents")
"""Those of the critics too: they see every agent, and which one is theirs (`bitcomm.commands.variance` runs them)."""


class _DefaultInt(int):
    """An int default that argparse passes through untouched: the flag was not given."""


class _DefaultFloat(float):
    """A float default that argparse passes through untouched: the flag was not given."""


def mark_task_defaults(parser: argparse.ArgumentParser) -> None:
    """Tag the task flags' defaults so `resolve_task` can tell them from values the user typed.

    Help text still shows the plain number (the tags are int/float subclasses).
    """
    for dest in TASK_FLAGS:
        value = parser.get_default(dest)
        if isinstance(value, bool) or value is None:
            continue
        if isinstance(value, int):
            parser.set_defaults(**{dest: _DefaultInt(value)})
        elif isinstance(value, float):
            parser.set_defaults(**{dest: _DefaultFloat(value)})


def given_task_flags(args: argparse.Namespace) -> dict[str, Any]:
    """The task flags typed on the command line, by dest (untagged values that are not None)."""
    out = {}
    for dest in TASK_FLAGS:
        value = getattr(args, dest, None)
        if value is not None and not isinstance(value, (_DefaultInt, _DefaultFloat)):
            out[dest] = value
    return out


def resolve_task(
    args: argparse.Namespace, base: TaskConfig, label: str = "RUN", fixed: tuple[str, ...] = ()
) -> TaskConfig:
    """`base` with the task flags the user gave applied; for a trained network, `fixed` (`POLICY_INPUTS` or
    `CRITIC_INPUTS`) names the flags it cannot take another value of, and the senders each agent hears must stay."""
    given = given_task_flags(args)
    changes: dict[str, dict[str, Any]] = {"env": {}, "channel": {}}
    for dest, value in given.items():
        part, name = TASK_FLAGS[dest]
        if dest in fixed and value != getattr(getattr(base, part), name):
            flag = dest.replace("_", "-")  # the flag typed (--agents), not the config's field (n_agents)
            raise bad_value(flag, value, f"{label} was trained with {flag}={getattr(getattr(base, part), name)}")
        changes[part][name] = value
    env: EnvConfig = dataclasses.replace(base.env, **changes["env"])
    channel: ChannelConfig = dataclasses.replace(base.channel, **changes["channel"])
    task = TaskConfig(env, channel)
    if fixed and task.slots != base.slots:  # the senders an agent hears are its network's message inputs too
        flag = "recipients" if "recipients" in given else "observes"
        raise bad_value(
            flag,
            given.get(flag),
            f"{label} was trained to hear {base.slots} sender(s) per agent; this would give {task.slots}",
        )
    return task


@lru_cache(maxsize=4)
def load_controller(run: str) -> Any:
    """`bitcomm.Controller.load(run)`, once per path; one error line when it cannot be done."""
    try:
        from bitcomm import Controller  # type: ignore[attr-defined]
    except ImportError:
        raise ConfigError(LEARNED_UNAVAILABLE) from None
    try:
        return Controller.load(run)
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(f"cannot load RUN {run!r}: {err}") from None


@lru_cache(maxsize=4)
def load_onnx(path: str) -> Any:
    """`OnnxController.load(path)`, once per path: what its card says (task, messages) is asked more than once."""
    from bitcomm.policies.onnx_policy import OnnxController

    return OnnxController.load(path)


@dataclass(frozen=True)
class PolicySource:
    """A per-agent policy to build: `name` is a reference policy, "run" with `run` a path, or "onnx"
    with `onnx` a file written by `bitcomm export`."""

    name: str = "oracle"
    run: str | None = None
    greedy: bool = False
    """Learned policies only: most likely move and message instead of sampling (how they were trained)."""
    onnx: str | None = None
    """An ONNX file written by `bitcomm export`, for `name="onnx"`: agents need onnxruntime, not torch."""

    def __post_init__(self) -> None:
        if self.name == "run" and not self.run:
            raise bad_value("RUN", self.run, "a run folder or checkpoint file is needed")
        if self.name == "onnx" and not self.onnx:
            raise bad_value("onnx", self.onnx, "an ONNX file written by bitcomm export is needed")
        if self.name not in ("run", "onnx") and self.name not in REFERENCE_POLICIES:
            raise bad_value("policy", self.name, f"choose one of {', '.join(REFERENCE_POLICIES)}, or give RUN")

    @property
    def label(self) -> str:
        return {"run": self.run, "onnx": self.onnx}.get(self.name) or self.name

    def _learned(self) -> Any:
        """The learned policy's controller, loaded once per path (None for a reference policy)."""
        if self.name == "run":
            return load_controller(self.run)
        if self.name == "onnx":
            return load_onnx(str(self.onnx))
        return None

    def base_task(self) -> TaskConfig:
        """The task the policy belongs to: its training task for a learned one, the paper's defaults otherwise."""
        learned = self._learned()
        return TaskConfig() if learned is None else learned.task

    def onehot(self) -> bool:
        """Whether the policy sends one-hot messages: acting then holds tables of 2^K per agent and episode
        (`bitcomm.commands.flags.play_bytes`)."""
        learned = self._learned()
        return learned is not None and learned.messages == "onehot"

    def task_from_args(self, args: argparse.Namespace) -> TaskConfig:
        """The task to run: `base_task()` changed by the task flags the user gave."""
        fixed = POLICY_INPUTS if self.name in ("run", "onnx") else ()  # a learned network's inputs
        return resolve_task(args, self.base_task(), label=f"{self.name.upper()} {self.label!r}", fixed=fixed)

    def build(self, task: TaskConfig, seed: int | np.random.SeedSequence | None = None) -> AgentPolicy:
        """The policy, for `task`; `seed` drives a random policy's draws and a learned policy's sampling.

        A learned RUN gets a sampling stream of its own from `seed` (the network is loaded once and shared):
        with the loaded controller's one stream, each sweep point, or each deployed agent, would go on from
        where the last one left it, so the same task read differently at each point of a sweep and `--seed`
        changed only the episodes. An int seed samples as `bitcomm eval RUN --seed S` does."""
        if self.name == "oracle":
            return OracleAgent(task)
        if self.name == "random":
            return RandomAgent(task, seed)
        if self.name == "onnx":
            from bitcomm.policies.onnx_policy import OnnxController

            return ControllerAgent(OnnxController.load(str(self.onnx), seed=0 if seed is None else seed), self.greedy)
        loaded = load_controller(self.run)
        if seed is not None:
            loaded = loaded.with_seed(seed)
        return ControllerAgent(loaded, greedy=self.greedy)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PolicySource:
        return cls(**data)


def add_policy_flags(parser: argparse.ArgumentParser, several: bool = False, onnx: bool = False) -> None:
    """RUN (optional positional), `--policy` and `--greedy`; call after `add_task_flags`.

    `several`: `--policy` may repeat and adds to RUN (for comparisons); otherwise it is RUN or one name.
    `onnx`: also `--onnx FILE`, a policy exported by `bitcomm export` (instead of RUN or `--policy`).
    """
    parser.add_argument(
        "run_path", nargs="?", default=None, metavar="RUN", help="run folder or checkpoint file of a learned policy"
    )  # not `run`: the CLI dispatches on args.run
    if several:
        parser.add_argument(
            "--policy", action="append", choices=REFERENCE_POLICIES, default=None,
            help="reference policy to include (repeatable; default: oracle when no RUN)",
        )  # fmt: skip
    else:
        parser.add_argument(
            "--policy", choices=REFERENCE_POLICIES, default=None, help="reference policy (default: oracle when no RUN)"
        )
    if onnx:
        parser.add_argument(
            "--onnx", metavar="FILE", default=None, help="policy exported by bitcomm export, run with onnxruntime"
        )
    parser.add_argument("--greedy", action="store_true", help="learned policies: most likely move and message")
    mark_task_defaults(parser)


def sources_from_args(args: argparse.Namespace) -> list[PolicySource]:
    """Every policy named on the command line: RUN first, `--onnx`, then each `--policy` (oracle if none)."""
    names = args.policy if isinstance(args.policy, list) else ([args.policy] if args.policy else [])
    sources = [PolicySource("run", args.run_path, args.greedy)] if args.run_path else []
    if getattr(args, "onnx", None):
        sources.append(PolicySource("onnx", greedy=args.greedy, onnx=args.onnx))
    sources += [PolicySource(name, None, args.greedy) for name in dict.fromkeys(names)]
    return sources or [PolicySource("oracle")]


def source_from_args(args: argparse.Namespace) -> PolicySource:
    """The one policy of a command that runs one: RUN, `--policy` or `--onnx`, not two of them."""
    given = {"RUN": args.run_path, "policy": args.policy, "onnx": getattr(args, "onnx", None)}
    named = [flag for flag, value in given.items() if value]
    if len(named) > 1:
        either = "RUN, --policy or --onnx" if "onnx" in args else "RUN or --policy"
        raise bad_value(named[1], given[named[1]], f"give either {either}, not both")
    return sources_from_args(args)[0]
