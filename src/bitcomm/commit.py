"""Which commit of bitcomm a folder of its source is: the commit of the git checkout that tracks it, and
whether the folder differs from it. A run asks git live about the code it runs from (`bitcomm.provenance`);
a build asks about the source tree it builds and bakes the answer into the built package as `BUILT`
(setup.py), so that an installed copy, which no checkout tracks, still names the commit it was built from.

Standard library only: setup.py loads this file by its path, where bitcomm's dependencies are not installed.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

BUILT = "_build.json"
"""The file a build writes into the built package: `{"git_commit": ..., "git_dirty": ...}`."""


def _git(folder: Path, *args: str) -> subprocess.CompletedProcess[str] | None:
    """`git ARGS` run in `folder`; None where git is missing or hangs."""
    try:
        return subprocess.run(["git", *args], capture_output=True, text=True, timeout=5, cwd=folder)
    except (OSError, subprocess.SubprocessError):
        return None


def of(folder: Path) -> tuple[str | None, bool | None]:
    """The commit of the checkout whose git tracks the package `folder` and whether the folder differs from it
    (a changed, staged, deleted or untracked file under it); (None, None) where git does not track its
    `__init__.py` (an installed copy, even one inside another project's repository, or an unpacked sdist)."""
    tracked = _git(folder, "ls-files", "--error-unmatch", "__init__.py")
    head = _git(folder, "rev-parse", "HEAD") if tracked is not None and tracked.returncode == 0 else None
    commit = head.stdout.strip() if head is not None and head.returncode == 0 else ""
    if not commit:
        return None, None
    status = _git(folder, "status", "--porcelain", "--", ".")
    return commit, None if status is None or status.returncode != 0 else bool(status.stdout.strip())


def bake(source: Path, built: Path) -> None:
    """Write `BUILT` into the built package folder `built`, naming the commit of the package's `source` folder, or
    where git knows none, the commit an sdist's source was baked with (an unpacked sdist, as `python -m build`
    builds its wheel from); none where neither is known (then the installed copy records None), not even an
    earlier build's."""
    commit, dirty = of(source)
    if commit is None:
        commit, dirty = baked(source)
    if commit is None:
        (built / BUILT).unlink(missing_ok=True)
    else:
        (built / BUILT).write_text(json.dumps({"git_commit": commit, "git_dirty": dirty}) + "\n")


def baked(package: Path) -> tuple[str | None, bool | None]:
    """The commit and dirtiness `bake` wrote into an installed `package`; (None, None) where it wrote nothing
    (or the file is not what `bake` writes)."""
    try:
        found = json.loads((package / BUILT).read_text())
    except (OSError, ValueError):
        return None, None
    commit = found.get("git_commit") if isinstance(found, dict) else None
    dirty = found.get("git_dirty")
    if not isinstance(commit, str):
        return None, None
    return commit, dirty if isinstance(dirty, bool) else None
