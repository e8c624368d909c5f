"""bitcomm: multi-agent reinforcement learning with learned discrete, noisy communication.

The public names load lazily, so `import bitcomm` (and the CLI) start without importing torch.
"""

from __future__ import annotations

from importlib import metadata as _metadata
from typing import TYPE_CHECKING

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig

if TYPE_CHECKING:
    from bitcomm.envs.channel_wrapper import BitChannel
    from bitcomm.learn.env_controller import EnvController
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate

try:
    __version__ = _metadata.version("bitcomm")
except _metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0"

__all__ = [
    "BitChannel",
    "ChannelConfig",
    "Controller",
    "EnvConfig",
    "EnvController",
    "TaskConfig",
    "evaluate",
    "__version__",
]

_LAZY = {
    "BitChannel": "bitcomm.envs.channel_wrapper",
    "Controller": "bitcomm.policies.controller",
    "EnvController": "bitcomm.learn.env_controller",
    "evaluate": "bitcomm.policies.evaluation",
}

if not TYPE_CHECKING:  # a type checker reads the imports above, so a name bitcomm lacks is an error there too

    def __getattr__(name: str):
        if name in _LAZY:
            import importlib

            return getattr(importlib.import_module(_LAZY[name]), name)
        raise AttributeError(f"module 'bitcomm' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public names, the lazy ones included, so that `dir(bitcomm)` and a notebook's tab completion show
    them (and not this module's helpers)."""
    return sorted({*__all__, *(n for n in globals() if not n.startswith("_") or n.startswith("__"))})
