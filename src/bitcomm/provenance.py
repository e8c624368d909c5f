"""What produced a result: the code (git commit, and whether it had uncommitted changes), the libraries, the
machine, the torch threads and the command, recorded by every run's config.json and every study's
provenance.json, so that a figure in a paper can be traced to what made it.

The commit is bitcomm's own: git is asked only where this package's source is a file that git tracks (a
source checkout, or an editable install of one), and a checkout with uncommitted changes to the package's
source says so in `git_dirty`: a commit alone would claim code that did not run. An install in site-packages
records the commit it was built from, which the build baked into it (`bitcomm.commit`), else None, never the
commit of a repository that happens to hold the virtual environment (a project's `.venv`).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from bitcomm import commit
from bitcomm.files import write_text_atomic

PACKAGE = Path(__file__).resolve().parent
"""The folder this bitcomm's code runs from."""
PROVENANCE = "provenance.json"
"""The file a study writes beside its results (`write`)."""
LIBRARIES = ("torch", "numpy", "gymnasium", "pettingzoo")
"""Libraries every run uses, whose versions are always recorded."""
OPTIONAL = ("mpe2", "ray", "onnx", "onnxruntime")
"""Libraries recorded where the process has loaded them (a wrapped env's, a backend's)."""
RECORDED = ("time", "git_commit", "git_dirty", "versions", "torch_threads", "machine", "command")
"""The keys of `record`."""


def git_state() -> tuple[str | None, bool | None]:
    """The commit this package's code is and whether its source differs from it: asked of git where its source
    is tracked by git (a checkout, or an editable install of one), else the commit an installed copy was built
    from, baked into it by the build (`bitcomm.commit`); (None, None) where neither is known (an installed copy
    built without git, even one inside another project's repository)."""
    live = commit.of(PACKAGE)
    return live if live[0] is not None else commit.baked(PACKAGE)


def versions() -> dict[str, str]:
    """Python's, bitcomm's and `LIBRARIES`' versions, and those of `OPTIONAL` loaded in this process."""
    from bitcomm import __version__

    found = {"python": platform.python_version(), "bitcomm": __version__}
    for name in (*LIBRARIES, *(n for n in OPTIONAL if n in sys.modules)):
        with contextlib.suppress(metadata.PackageNotFoundError):
            found[name] = metadata.version(name)
    if "torch" in sys.modules:  # the build that ran ("2.4.0+cpu"), which the metadata may not name
        found["torch"] = sys.modules["torch"].__version__
    return found


def machine() -> dict[str, Any]:
    """What ran a run, so that its seconds can be set beside another run's: the CPU's model (Linux's
    /proc/cpuinfo, else `platform.processor()`), its logical cores, the OS and the architecture."""
    cpu = platform.processor() or "unknown"
    with contextlib.suppress(OSError):
        models = (line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name"))  # fmt: skip
        cpu = next(models, cpu)
    return {"cpu": cpu, "cores": os.cpu_count(), "system": platform.system(), "arch": platform.machine()}


def record() -> dict[str, Any]:
    """This process's provenance: time, git commit and whether it was dirty, versions, torch threads, machine
    and command line."""
    import torch

    git_commit, git_dirty = git_state()
    return {
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "git_commit": git_commit,
        "git_dirty": git_dirty,
        "versions": versions(),
        "torch_threads": torch.get_num_threads(),
        "machine": machine(),
        "command": sys.argv,
    }


def write(out: Path, settings: dict[str, Any]) -> Path:
    """`<out>/provenance.json`: a study's `settings` (its flags, as parsed) with `record()`, written atomically."""
    path = Path(out) / PROVENANCE
    write_text_atomic(path, json.dumps({"settings": settings, **record()}, indent=2, default=str) + "\n")
    return path
