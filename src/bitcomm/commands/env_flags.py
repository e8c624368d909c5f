"""The flags of `bitcomm train --env`: train on any PettingZoo env wrapped in bitcomm's channel.

Torch-free (every command builds every parser). The channel's K, delay and noise are the task flags
`--bits --delay --flip-prob --drop-prob`; learning options are the usual learning flags (`--entropy-move`
weights the entropy of the env's own actions). Values are JSON where they are structured, each checked
while argparse parses, so a typo is one line naming the flag.
"""

from __future__ import annotations

import argparse
import json
from typing import Any


def _json(text: str, what: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: must be {what} in JSON") from None


def env_spec(text: str) -> str:
    """`package.module:factory`; whether it imports is checked when the run starts."""
    module, colon, factory = text.partition(":")
    if not colon or not module.strip() or not factory.strip() or ":" in factory:
        raise argparse.ArgumentTypeError(
            f"invalid value {text!r}: must be PACKAGE.MODULE:FACTORY, e.g. mpe2.simple_speaker_listener_v4:parallel_env"
        )
    return text


def json_object(text: str) -> dict[str, Any]:
    value = _json(text, "an object")
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: must be an object in JSON, e.g. '{{\"N\": 3}}'")
    return value


def topology(text: str) -> str | list[list[str]]:
    """`all`, `ring`, or a JSON list of [sender, receiver] agent-name pairs."""
    if text in ("all", "ring"):
        return text
    value = _json(text, "all, ring, or a list of [sender, receiver] pairs")
    if not isinstance(value, list) or not all(
        isinstance(e, list) and len(e) == 2 and all(isinstance(a, str) for a in e) for e in value
    ):
        raise argparse.ArgumentTypeError(
            f"invalid value {text!r}: must be all, ring, or a JSON list of [sender, receiver] agent names"
        )
    return value


json_object.__name__ = "json_object"
topology.__name__ = "topology"
env_spec.__name__ = "env_spec"


def add_env_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("a wrapped PettingZoo env instead of the grid (docs/env_learning.md)")
    g.add_argument(
        "--env",
        type=env_spec,
        default=None,
        help="PACKAGE.MODULE:FACTORY returning a PettingZoo ParallelEnv with (Multi)Discrete, MultiBinary or Box "
        "actions (e.g. mpe2.simple_speaker_listener_v4:parallel_env); default: the grid task",
    )
    g.add_argument(
        "--env-kwargs", type=json_object, default=None, help="the factory's keyword arguments, a JSON object"
    )
    g.add_argument(
        "--topology",
        type=topology,
        default=None,
        help="who hears whom: all, ring, or JSON [[sender, receiver], ...] (default: all)",
    )
    g.add_argument(
        "--fixed-actions",
        type=json_object,
        default=None,
        help="agents whose own action is fixed, a JSON object, e.g. '{\"speaker_0\": 0}' (default: none)",
    )
    g.add_argument(
        "--obs-norm",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="standardise observations and state by running statistics (default: off)",
    )
    g.add_argument(
        "--env-workers",
        type=int,
        default=None,
        help="step the env copies in W worker processes (slow envs); the same episodes (default 0: in this process)",
    )


ENV_ONLY = ("env_kwargs", "topology", "fixed_actions", "obs_norm", "env_workers")
"""Flags that mean something only with --env."""
