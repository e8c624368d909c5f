"""The build, as pyproject.toml declares it, plus one step: a built package (a wheel, `pip install .`) and an
sdist's source get `bitcomm/_build.json`, the commit of the checkout they were built from, which an installed copy's
runs record (`bitcomm.commit`); a wheel built from an unpacked sdist (`python -m build`) keeps the sdist's. An
editable install gets none: it asks git live. Nothing is written into the checkout's src/."""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

SOURCE = Path(__file__).resolve().parent / "src" / "bitcomm"


def bake(built: Path) -> None:
    spec = importlib.util.spec_from_file_location("bitcomm_commit", SOURCE / "commit.py")
    assert spec is not None and spec.loader is not None
    commit = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(commit)
    commit.bake(SOURCE, built)


class BuildWithCommit(build_py):
    def run(self) -> None:
        super().run()
        if not self.editable_mode:
            bake(Path(self.build_lib) / "bitcomm")


class SdistWithCommit(sdist):
    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        bake(Path(base_dir) / "src" / "bitcomm")


setup(cmdclass={"build_py": BuildWithCommit, "sdist": SdistWithCommit})
