"""The build, as pyproject.toml declares it, plus one step: a built package (a wheel, `pip install .`) gets
`bitcomm/_build.json`, the commit of the checkout it was built from, which an installed copy's runs record
(`bitcomm.commit`). An editable install gets none: it asks git live. Nothing is written into src/."""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

SOURCE = Path(__file__).resolve().parent / "src" / "bitcomm"


class BuildWithCommit(build_py):
    def run(self) -> None:
        super().run()
        if not self.editable_mode:
            spec = importlib.util.spec_from_file_location("bitcomm_commit", SOURCE / "commit.py")
            assert spec is not None and spec.loader is not None
            commit = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(commit)
            commit.bake(SOURCE, Path(self.build_lib) / "bitcomm")


setup(cmdclass={"build_py": BuildWithCommit})
