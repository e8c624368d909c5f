"""Building bitcomm: a wheel (`pip wheel .`, or `pip install .`, which builds one) carries the commit of the
checkout it was built from in `bitcomm/_build.json`, so that an installed copy's runs record it."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest
from tests.test_run_folder import git

from bitcomm.commit import BUILT

ROOT = Path(__file__).resolve().parents[1]


def can_build_wheels() -> bool:
    """The build runs without isolation (which would download setuptools), so it needs this environment's
    setuptools and its wheel builder (in setuptools since 70.1, else the `wheel` package)."""
    if importlib.util.find_spec("setuptools") is None:
        return False
    return any(importlib.util.find_spec(name) is not None for name in ("setuptools.command.bdist_wheel", "wheel"))


pytestmark = [
    pytest.mark.skipif(shutil.which("git") is None, reason="needs git"),
    pytest.mark.skipif(not can_build_wheels(), reason="needs setuptools>=70.1 (or wheel) to build without network"),
]


def committed_source(tmp_path: Path) -> Path:
    """This tree's build files, committed in a repository of their own: the commit is known, the repo untouched."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    shutil.copytree(ROOT / "src" / "bitcomm", source / "src" / "bitcomm", ignore=shutil.ignore_patterns("__pycache__"))
    git(source, "init", "-q")
    git(source, "add", ".")
    git(source, "commit", "-qm", "bitcomm")
    return source


def baked_in_wheel(source: Path, wheels: Path) -> dict[str, object]:
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
         "--disable-pip-version-check", "-w", str(wheels), str(source)],
        check=True, capture_output=True, cwd=wheels.parent,
    )  # fmt: skip
    (wheel,) = wheels.glob("bitcomm-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        return dict(json.loads(archive.read(f"bitcomm/{BUILT}")))


def test_a_built_wheel_names_the_commit_it_was_built_from(tmp_path: Path) -> None:
    source = committed_source(tmp_path)
    baked = baked_in_wheel(source, tmp_path / "wheels")
    assert baked == {"git_commit": git(source, "rev-parse", "HEAD"), "git_dirty": False}


def test_a_wheel_built_from_an_sdist_keeps_the_commit_the_sdist_was_made_from(tmp_path: Path) -> None:
    """`python -m build` makes the sdist, then the wheel from the unpacked sdist, which no checkout tracks."""
    source = committed_source(tmp_path)
    made = subprocess.run(
        [sys.executable, "-c", "import setuptools.build_meta as b; print(b.build_sdist('dist'))"],
        cwd=source, check=True, capture_output=True, text=True,
    )  # fmt: skip
    with tarfile.open(source / "dist" / made.stdout.strip().splitlines()[-1]) as archive:
        archive.extractall(tmp_path / "unpacked", filter="data")
    (unpacked,) = (tmp_path / "unpacked").iterdir()
    baked = baked_in_wheel(unpacked, tmp_path / "wheels")
    assert baked == {"git_commit": git(source, "rev-parse", "HEAD"), "git_dirty": False}
