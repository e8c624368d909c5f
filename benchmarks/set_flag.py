"""`--set NAME=VALUE`, any learning option of `bitcomm train` by its field name, for the benchmarks that train."""

from __future__ import annotations

import argparse
from typing import Any


def add_set_flag(ap: argparse.ArgumentParser) -> None:
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a learning option, as `bitcomm train --help` lists them (field names: num_envs)",
    )


def parse_set(ap: argparse.ArgumentParser, items: list[str]) -> list[tuple[str, Any]]:
    """The `--set` items as (field, value): an unknown name exits with the parser's one error line; a bad value
    raises the option's ConfigError, for the caller to report with its other checks."""
    from bitcomm.learn.options import learning_options

    options = learning_options()
    pairs = [item.partition("=")[::2] for item in items]
    for item, (name, value) in zip(items, pairs, strict=True):
        if name not in options or not value:
            ap.error(f"--set {item!r}: expected NAME=VALUE with NAME one of {', '.join(sorted(options))}")
    return [(name, options[name].parse(value)) for name, value in pairs]
