"""Build a PettingZoo env from a text spec `"package.module:factory"` (what `bitcomm train --env` takes).

A spec names a callable that returns a `ParallelEnv`, e.g. `mpe2.simple_speaker_listener_v4:parallel_env`;
keyword arguments come from JSON (`--env-kwargs`). Every way this can go wrong for a user (a module that
does not import, a missing factory, a factory that fails or returns something else) is one line.

Making an env runs code: the spec's module is imported and its factory called. A spec the user typed is theirs
to run; a spec *read from a file* (a run folder's checkpoint, which anyone may have written) is built only when
it is trusted (`check_recorded_env`), as a pickle from an untrusted file is never loaded.
"""

from __future__ import annotations

import functools
import importlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pettingzoo import ParallelEnv

from bitcomm.errors import bad_value, one_line

TRUSTED_PACKAGES = ("mpe2", "pettingzoo")
"""Env packages whose factories a recorded spec may name without the user saying so: the ones the docs use."""
TRUST_VARIABLE = "BITCOMM_TRUST_ENVS"
"""Comma-separated top-level packages the user trusts as well (their own envs), e.g. `mypkg,labenvs`."""


def split_spec(spec: str) -> tuple[str, str]:
    """(module, factory) of `"package.module:factory"`, read without importing anything."""
    if not isinstance(spec, str) or spec.count(":") != 1 or not all(spec.split(":")):
        raise bad_value(
            "env", spec, "must be PACKAGE.MODULE:FACTORY, e.g. mpe2.simple_speaker_listener_v4:parallel_env"
        )
    module_name, attr = spec.split(":")
    return module_name, attr


def trusted_packages() -> tuple[str, ...]:
    """`TRUSTED_PACKAGES` and those listed in `BITCOMM_TRUST_ENVS`."""
    listed = (name.strip() for name in os.environ.get(TRUST_VARIABLE, "").split(","))
    return (*TRUSTED_PACKAGES, *(name for name in listed if name))


def check_recorded_env(spec: str, source: Path | str, typed: str | None = None) -> None:
    """Refuse to build an env whose spec was read from `source` (a file anyone may have written, as a pickle)
    unless the user vouched for it: typed it on this command (`typed`), or its package is trusted. Checked before
    anything is imported; for a trusted package, the factory must also be defined in a trusted package (not a
    function such a module merely imported, `os.system` say)."""
    if typed is not None and typed == spec:
        return
    module_name, attr = split_spec(spec)
    package, trusted = module_name.split(".")[0], trusted_packages()
    if package not in trusted:
        raise bad_value(
            "env", spec, f"read from {source}: making it imports {module_name!r} and calls {attr!r} with the run's "
            f"env_kwargs, code the run folder chooses; {_how_to_trust(spec, package)}"
        )  # fmt: skip
    factory = resolve_factory(spec)
    while isinstance(factory, functools.partial):  # its own __module__ is functools: where the code it calls is
        factory = factory.func
    home = str(getattr(factory, "__module__", None) or "?")
    if home.split(".")[0] not in trusted:
        raise bad_value(
            "env", spec, f"read from {source}: {attr!r} is defined in {home!r}, outside the trusted packages "
            f"({', '.join(trusted)}); {_how_to_trust(spec, home.split('.')[0])}"
        )  # fmt: skip


def _how_to_trust(spec: str, package: str) -> str:
    return (
        f"to trust it, type --env {spec} (train --resume; from Python, typed_env={spec!r}) or set "
        f"{TRUST_VARIABLE}={package}"
    )


def resolve_factory(spec: str) -> Callable[..., Any]:
    """The callable named by `"package.module:factory"`."""
    module_name, attr = split_spec(spec)
    try:
        module = importlib.import_module(module_name)
    except Exception as err:  # ImportError, or whatever the module raises while it loads
        raise bad_value("env", spec, f"module {module_name!r} cannot be imported ({one_line(err)})") from None
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
        raise bad_value("env_kwargs", kwargs or {}, f"{spec} failed with them ({one_line(err)})") from None
    if not isinstance(env, ParallelEnv):
        raise bad_value("env", spec, f"returned a {type(env).__name__}, not a PettingZoo ParallelEnv")
    return env
