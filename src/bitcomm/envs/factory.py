"""Build a PettingZoo env from a text spec `"package.module:factory"` (what `bitcomm train --env` takes).

A spec names a callable that returns a `ParallelEnv`, e.g. `mpe2.simple_speaker_listener_v4:parallel_env`;
keyword arguments come from JSON (`--env-kwargs`). Every way this can go wrong for a user (a module that
does not import, a missing factory, a factory that fails or returns something else) is one line.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from pettingzoo import ParallelEnv

from bitcomm.errors import bad_value


def resolve_factory(spec: str) -> Callable[..., Any]:
    """The callable named by `"package.module:factory"`."""
    if not isinstance(spec, str) or spec.count(":") != 1 or not all(spec.split(":")):
        raise bad_value(
            "env", spec, "must be PACKAGE.MODULE:FACTORY, e.g. mpe2.simple_speaker_listener_v4:parallel_env"
        )
    module_name, attr = spec.split(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as err:  # ImportError, or whatever the module raises while it loads
        raise bad_value(
            "env", spec, f"module {module_name!r} cannot be imported ({type(err).__name__}: {err})"
        ) from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise bad_value("env", spec, f"module {module_name!r} has no callable {attr!r}")
    return factory


def make_parallel_env(spec: str, kwargs: dict[str, Any] | None = None) -> ParallelEnv:
    """Call the factory `spec` names with `kwargs`; the result must be a PettingZoo `ParallelEnv`."""
    if kwargs is not None and not isinstance(kwargs, dict):
        raise bad_value("env_kwargs", kwargs, "must be a JSON object of keyword arguments")
    factory = resolve_factory(spec)
    try:
        env = factory(**(kwargs or {}))
    except Exception as err:  # a bad keyword or value for this env
        raise bad_value("env_kwargs", kwargs or {}, f"{spec} failed with them ({type(err).__name__}: {err})") from None
    if not isinstance(env, ParallelEnv):
        raise bad_value("env", spec, f"returned a {type(env).__name__}, not a PettingZoo ParallelEnv")
    return env
