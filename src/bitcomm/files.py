"""Writing a file so that a reader, or a run killed or out of disk space midway, never finds half of it.

`write_atomic` writes to a temporary name in the same folder and renames it into place (atomic on POSIX):
the old file stays whole until the new one is complete. A write that fails (a full disk, a quota, a folder
made read-only) removes its temporary file and raises the `OSError`; one killed outright leaves it, named
`.<name>.tmp<pid>`, for `bitcomm.checkpoint.clean` to remove when the run starts again. Light on purpose
(no torch): the CLI's provenance records and a study's tables use it too.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path


def temporary(path: Path) -> Path:
    """Where `write_atomic` writes `path` first: hidden, and this process's own (two writers never share it)."""
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


@contextlib.contextmanager
def naming(path: Path, *aliases: Path) -> Iterator[None]:
    """An `OSError` raised in the block names `path` where it names no file or one of `aliases` (a buffered
    write's error names no file, and a temporary name means nothing to a user)."""
    try:
        yield
    except OSError as err:
        if err.filename is None or str(err.filename) in map(str, aliases):
            err.filename = str(path)
        raise


def write_atomic(path: Path, write: Callable[[Path], object]) -> None:
    """`write(tmp)`, then rename `tmp` over `path`; on any failure `tmp` is removed and `path` is as it was. An
    `OSError` names `path` (`naming`)."""
    tmp = temporary(path)
    try:
        with naming(path, tmp):
            write(tmp)
            os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):  # gone once renamed; never hide why the write failed
            tmp.unlink(missing_ok=True)


def write_text_atomic(path: Path, text: str) -> None:
    """`write_atomic` of a text file."""
    write_atomic(path, lambda tmp: tmp.write_text(text))
