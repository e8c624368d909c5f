"""Where `bitcomm train` runs: `--address` of a Ray cluster, and how a resumed run is executed.

`--backend`, `--workers` and `--staleness` are learning options (fields of TrainConfig, so
`bitcomm.commands.learning_flags` makes their flags); they say how a run is executed, not what it learns,
so `--resume` takes them from the command line: a run resumes locally unless `--backend ray` is given
again, whatever backend it started on. Torch-free, like every parser.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
from typing import TYPE_CHECKING

from bitcomm.errors import bad_value

if TYPE_CHECKING:
    from bitcomm.learn.config import TrainConfig

ADDRESS = re.compile(r"(ray://)?[A-Za-z0-9._\-\[\]:]*[A-Za-z0-9\]]:(\d{1,5})")
"""`HOST:PORT` of a head node's GCS (as `ray start --head` prints it) or `ray://HOST:PORT` of a Ray client."""


def ray_address(text: str) -> str:
    """An argparse type: `auto` (the cluster `ray start` left on this machine), `HOST:PORT` or `ray://HOST:PORT`."""
    match = ADDRESS.fullmatch(text.strip())
    if text.strip() == "auto" or (match and 1 <= int(match.group(2)) <= 65535):
        return text.strip()
    raise argparse.ArgumentTypeError(f"invalid value {text!r}: must be auto, HOST:PORT or ray://HOST:PORT")


def add_backend_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--address",
        type=ray_address,
        default=None,
        help="the Ray cluster to train on with --backend ray (default: a Ray instance started on this machine)",
    )


def execution(args: argparse.Namespace, cfg: TrainConfig) -> TrainConfig:
    """`cfg` as this command line runs it: on `--resume`, the backend (default local), workers and staleness
    given now; one line for `--address` without `--backend ray`."""
    if args.resume:
        backend = args.backend or "local"
        staleness = args.staleness if args.staleness is not None else cfg.staleness if backend == "ray" else 0
        cfg = dataclasses.replace(cfg, backend=backend, workers=args.workers or cfg.workers, staleness=staleness)
    if args.address is not None and cfg.backend != "ray":
        raise bad_value("address", args.address, "only with --backend ray")
    return cfg
