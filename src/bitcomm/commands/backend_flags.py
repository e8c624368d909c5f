"""Where `bitcomm train` runs: `--address` of a Ray cluster, and how a resumed run is executed.

`--backend`, `--workers` and `--staleness` are learning options (fields of TrainConfig, so
`bitcomm.commands.learning_flags` makes their flags); they say how a run is executed, not what it learns,
so `--resume` takes them from the command line: a run resumes locally unless `--backend ray` is given
again, whatever backend it started on. So do the budget and how often it saves (`RESUME_MAY_CHANGE`); any
other flag typed with `--resume` must say what the run already is (`check_resume_flags`). Torch-free, like every
parser.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bitcomm.errors import bad_value
from bitcomm.learn.ray_address import ADDRESS_FORMS, host_port
from bitcomm.learn.resume_rules import RESUME_MAY_CHANGE

if TYPE_CHECKING:
    from bitcomm.learn.config import TrainConfig


def ray_address(text: str) -> str:
    """An argparse type: `auto` (the cluster `ray start` left on this machine), `HOST:PORT` or `ray://HOST:PORT`."""
    if text.strip() == "auto" or host_port(text) is not None:
        return text.strip()
    raise argparse.ArgumentTypeError(f"invalid value {text!r}: {ADDRESS_FORMS}")


def check_resume_flags(out: Path, typed: dict[str, Any], recorded: Callable[[str], Any]) -> None:
    """A resume continues a run as it started: one line for a flag typed with another value than the run's
    (`recorded(name)`; `typed` by option name), rather than a run that silently ignores it."""
    for name, value in typed.items():
        was = recorded(name)
        if name not in RESUME_MAY_CHANGE and _plain(value) != _plain(was):
            flag = name.replace("_", "-")
            raise bad_value(
                flag,
                value,
                f"the run in {str(out)!r} was trained with {flag}={was}, and --resume continues it as it started "
                "(only the budget, where it runs and how often it saves may change)",
            )


def _plain(value: Any) -> Any:
    """A value as config.json gives it back (a tuple as a list), so a typed value and a recorded one compare."""
    return [_plain(v) for v in value] if isinstance(value, (list, tuple)) else value


def add_backend_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--address",
        type=ray_address,
        default=None,
        help="the Ray cluster to train on with --backend ray: auto (RAY_ADDRESS, else the last `ray start` here), "
        "HOST:PORT or ray://HOST:PORT (default: a Ray instance started on this machine)",
    )


def execution(args: argparse.Namespace, cfg: TrainConfig) -> TrainConfig:
    """`cfg` as this command line runs it: on `--resume`, the backend (default local), workers and staleness
    given now; one line for `--address` without `--backend ray`, and for an a3c run resumed on Ray."""
    if args.resume:
        backend = args.backend or "local"
        if backend == "ray" and cfg.mode != "sync":  # not the config's own line, which says to change the mode
            raise bad_value(
                "backend",
                backend,
                f"the run was trained with mode={cfg.mode}, which trains on the local backend only (Ray's actors play "
                "sync batches), and --resume keeps its mode: resume it without --backend ray",
            )
        staleness = args.staleness if args.staleness is not None else cfg.staleness if backend == "ray" else 0
        cfg = dataclasses.replace(cfg, backend=backend, workers=args.workers or cfg.workers, staleness=staleness)
    if args.address is not None and cfg.backend != "ray":
        raise bad_value("address", args.address, "only with --backend ray")
    return cfg
