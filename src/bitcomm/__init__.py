"""bitcomm: multi-agent reinforcement learning with learned discrete, noisy communication.

The public names load lazily, so `import bitcomm` (and the CLI) start without importing torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig

if TYPE_CHECKING:
    from bitcomm.envs.channel_wrapper import BitChannel
    from bitcomm.learn.env_controller import EnvController
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate

try:
    from importlib.metadata import PackageNotFoundError, version

    __version__ = version("bitcomm")
except PackageNotFoundError:  # running from a source tree that is not installed
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


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'bitcomm' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The lazy names too, so that `dir(bitcomm)` and a notebook's tab completion show them."""
    return sorted({*globals(), *_LAZY})
