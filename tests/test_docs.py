"""What the README and docs/ tell a user to type: every `bitcomm` command in their code blocks parses with the real
parser (nothing is run), and the command answers `--version`, `help`, no arguments and `python -m bitcomm`.

docs/tuning.md and docs/history.md are logs of past sessions, whose commands may name flags since renamed; they
are left out. In the others a seed written `S` and an optional flag written `[--flag]` stand for any seed and the
flag itself.
"""

from __future__ import annotations

import contextlib
import csv
import io
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from bitcomm import __version__
from bitcomm.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
LOGS = ("tuning.md", "history.md")
DOCS = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").glob("*.md") if p.name not in LOGS)]


def shell_lines(block: list[str]) -> Iterator[str]:
    """A code block's lines as the shell reads them: `\\` continues a line, as does an open quote."""
    buf = ""
    for line in block:
        buf += line
        if buf.endswith("\\"):
            buf = buf[:-1] + " "
            continue
        try:
            shlex.split(buf, comments=True)
        except ValueError:  # an open quote: the value goes on to the next line
            buf += "\n"
            continue
        yield buf
        buf = ""


def statements(line: str) -> Iterator[list[str]]:
    """The words of each `;`-separated statement of a shell line, its comment dropped."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";")
    lexer.whitespace_split = True
    words: list[str] = []
    for word in lexer:
        if word == ";":
            yield words
            words = []
        else:
            words.append(word)
    yield words


def commands() -> Iterator[tuple[str, list[str]]]:
    """(where, argv after `bitcomm`) for every `bitcomm` command of every bash block, shell variables expanded."""
    for path in DOCS:
        text = path.read_text()
        for block in re.finditer(r"^```bash\n(.*?)^```", text, flags=re.S | re.M):
            line_no = text[: block.start()].count("\n") + 2
            variables: dict[str, str] = {}
            for line in shell_lines(block.group(1).splitlines()):
                line = re.sub(r"\[(--[^\]]*)\]", r"\1", line).replace(" --seed S ", " --seed 0 ")
                for words in statements(line):
                    if len(words) == 1 and re.fullmatch(r"\w+=.*", words[0], flags=re.S):
                        name, value = words[0].split("=", 1)
                        variables[name] = value
                        continue
                    if "bitcomm" not in words:
                        continue
                    argv = []
                    for word in words[words.index("bitcomm") + 1 :]:
                        bare = word.lstrip("$")
                        if word.startswith("$") and bare in variables:  # unquoted: split on whitespace
                            argv += variables[bare].split()
                        else:
                            for name, value in variables.items():
                                word = word.replace(f"${name}", value)
                            argv.append(word)
                    yield f"{path.name}:{line_no}", argv


COMMANDS = list(commands())


def test_the_docs_have_commands_to_check() -> None:
    assert len(COMMANDS) > 100
    assert {where.split(":")[0] for where, _ in COMMANDS} >= {"README.md", "results.md", "robots.md", "distributed.md"}


@pytest.mark.parametrize(("where", "argv"), COMMANDS, ids=[f"{w} {' '.join(a)[:80]}" for w, a in COMMANDS])
def test_every_documented_command_parses(where: str, argv: list[str]) -> None:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            _, unknown = build_parser().parse_known_args(argv)
        except SystemExit as exit_:
            pytest.fail(f"{where}: bitcomm {' '.join(argv)}\n{err.getvalue()} (exit {exit_.code})")
    assert not unknown, f"{where}: bitcomm {' '.join(argv)}: unrecognized {unknown}"


def test_version_help_and_no_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"bitcomm {__version__}"
    assert main([]) == 2  # no command: the commands listed, not a one-line error
    assert "train agents to act and communicate" in capsys.readouterr().err
    assert main(["help"]) == 0 and "{analyze,baseline," in capsys.readouterr().out
    assert main(["help", "train"]) == 0 and "--episodes" in capsys.readouterr().out
    assert main(["help", "nope"]) == 2 and "invalid choice: 'nope'" in capsys.readouterr().err


def test_python_m_bitcomm_is_the_command() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "bitcomm", "--version"], capture_output=True, text=True, env=os.environ, timeout=60
    )
    assert (out.returncode, out.stdout.strip()) == (0, f"bitcomm {__version__}"), out.stderr


def test_dir_lists_every_public_name() -> None:
    """The lazily loaded names too (BitChannel, Controller, evaluate): a notebook's tab completion reads dir()."""
    import bitcomm

    assert set(bitcomm.__all__) <= set(dir(bitcomm))
    assert not {"Any", "version", "PackageNotFoundError"} & set(dir(bitcomm))  # helpers of the module, not names


def test_a_type_checker_sees_the_lazy_names_typed_and_refuses_a_name_bitcomm_lacks(tmp_path: Path) -> None:
    """The package ships `py.typed`: a user's mypy must type `bitcomm.Controller.load` (not Any, as a module
    `__getattr__` would make every name) and flag a typo such as `bitcomm.train`, which fails at run time."""
    out = user_mypy(tmp_path, "import bitcomm\n\nreveal_type(bitcomm.Controller.load)\nbitcomm.train\n")
    assert "-> bitcomm.policies.controller.Controller" in out, out
    assert 'Module has no attribute "train"' in out, out


def user_mypy(tmp_path: Path, code: str, skip: tuple[str, ...] = ("torch", "numpy", "gymnasium", "pettingzoo")) -> str:
    """mypy's report on a user's script `code` that imports bitcomm from this source tree (the packages `skip`
    names read as Any, which is quicker)."""
    from mypy import api

    src = Path(__file__).resolve().parents[1] / "src"
    skipped = "".join(f"[mypy-{m}.*]\nfollow_imports = skip\n" for m in skip)
    (tmp_path / "mypy.ini").write_text(f"[mypy]\nmypy_path = {src}\nfollow_imports = silent\n{skipped}")
    (tmp_path / "user.py").write_text(code)
    out, _, _ = api.run(["--config-file", str(tmp_path / "mypy.ini"), "--cache-dir", str(tmp_path / "cache"),
                         str(tmp_path / "user.py")])  # fmt: skip
    return out


def test_a_type_checker_takes_a_topology_as_tuples_or_as_lists_where_bitcomm_does(tmp_path: Path) -> None:
    """`BitChannel` and `EnvChannelConfig` take `(sender, receiver)` pairs as tuples (docs/channel_wrapper.md) and as
    lists (JSON's, docs/env_learning.md) alike, but were annotated with one each: a typed user's mypy refused the
    other form, which runs."""
    code = """from typing import Any
from bitcomm import BitChannel
from bitcomm.learn.env_config import EnvChannelConfig

def check(env: Any) -> None:
    for pairs in ([("speaker_0", "listener_0")], [["speaker_0", "listener_0"]], (("speaker_0", "listener_0"),)):
        EnvChannelConfig(bits=3, topology=pairs)
        BitChannel(env, bits=3, topology=pairs)
"""
    out = user_mypy(tmp_path, code)
    assert "Success: no issues found" in out, out


def test_a_type_checker_takes_a_numpy_integer_seed_where_bitcomm_does(tmp_path: Path) -> None:
    """A seed or an episode count from numpy (`rng.integers()`, a sweep's `np.arange`) plays as the Python int
    (`check_seed`), but `evaluate`, `evaluate_env`, the controllers' `load` and `BitChannel` were annotated `int`: a
    typed user's mypy refused what runs."""
    code = """from typing import Any

import numpy as np
from bitcomm import Controller, EnvController, evaluate
from bitcomm.learn.env_eval import evaluate_env
from bitcomm.envs.channel_wrapper import BitChannel
from bitcomm.policies.onnx_policy import OnnxController

seed, episodes = np.int64(3), np.int64(20)
env: Any = None  # what the env is does not matter here, only the seed
BitChannel(env, seed=seed)
evaluate(Controller.load("runs/a", seed=seed), episodes=episodes, seed=seed)
evaluate_env("runs/e", episodes, seed=seed)
EnvController.load("runs/e", seed=seed)
OnnxController.load("policy.onnx", seed=seed)
"""
    out = user_mypy(tmp_path, code, skip=("torch", "gymnasium", "pettingzoo"))
    assert "Success: no issues found" in out, out


def python_blocks() -> Iterator[tuple[str, str]]:
    for path in DOCS:
        text = path.read_text()
        for block in re.finditer(r"^```python\n(.*?)^```", text, flags=re.S | re.M):
            yield f"{path.name}:{text[: block.start()].count(chr(10)) + 2}", block.group(1)


BLOCKS = list(python_blocks())


@pytest.mark.parametrize(("where", "source"), BLOCKS, ids=[w for w, _ in BLOCKS])
def test_every_python_snippet_compiles_and_its_imports_exist(where: str, source: str) -> None:
    """Running them would train for minutes; what a moved or renamed name breaks is caught by importing it."""
    import importlib.util

    compile(source, where, "exec")
    for module, names in re.findall(r"^from ([\w.]+) import ([\w, ]+)", source, flags=re.M):
        if module.split(".")[0] != "bitcomm" and importlib.util.find_spec(module.split(".")[0]) is None:
            continue  # an optional extra (mpe2, onnxruntime) that this environment lacks
        imported = importlib.import_module(module)
        for name in (n.strip() for n in names.split(",")):
            found = hasattr(imported, name) or importlib.util.find_spec(f"{module}.{name}") is not None  # a submodule
            assert found, f"{where}: from {module} import {name}"


def metrics_table() -> set[str]:
    """The columns README's table of metrics.csv lists (its first cell's names)."""
    text = (ROOT / "README.md").read_text()
    table = text[text.index("| column | what it holds |") :].split("\n\n")[0].splitlines()[2:]
    return {name for row in table for name in re.findall(r"`([\w/]+)`", row.split(" | ")[0])}


def test_the_readme_lists_every_metrics_column_a_run_writes(tmp_path: Path) -> None:
    """README's table of metrics.csv is the set of columns the trainers write: a grid run with every optional
    figure on (words to spare, held-out play, the move decay's wait), `--recipe supervised`'s auxiliary losses, a
    run on a wrapped env, and the Ray backend's own, read from the code that adds them (tests/test_ray.py trains
    on Ray)."""
    pytest.importorskip("mpe2")
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.learn import ray_backend
    from bitcomm.learn.config import make_train_config
    from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
    from bitcomm.learn.env_run import train_env
    from bitcomm.learn.run import train

    def grid(bits: int) -> TaskConfig:
        return TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=bits))

    optional = {"held_out_every": 16, "held_out_episodes": 8, "move_decay_below": 2.0}  # and 32 words, 16 cells
    every_figure = make_train_config("reinforced", grid(5), episodes=32, num_envs=16, **optional)
    train(every_figure, tmp_path / "grid", progress=False)
    train(make_train_config("supervised", grid(4), episodes=16, num_envs=16), tmp_path / "supervised", progress=False)
    env = EnvTrainConfig(
        env="mpe2.simple_speaker_listener_v4:parallel_env",
        env_kwargs={"max_cycles": 4},
        channel=EnvChannelConfig(bits=2),
        episodes=4,
        num_envs=4,
        entropy_message_marginal=0.1,
    )
    train_env(env, tmp_path / "env", progress=False)
    written = set(re.findall(r'"(ray/\w+)"', Path(ray_backend.__file__).read_text()))
    for run in ("grid", "supervised", "env"):
        with (tmp_path / run / "metrics.csv").open(newline="") as f:
            written |= set(next(csv.reader(f)))
    documented = metrics_table()
    assert not written - documented, f"README's metrics.csv table lacks {sorted(written - documented)}"
    assert not documented - written, f"README's metrics.csv table lists {sorted(documented - written)}, never written"


def test_the_env_flags_table_lists_the_learning_flags_an_env_run_takes() -> None:
    """docs/env_learning.md's "learning flags" row names exactly those `bitcomm train --env` takes; it refuses the
    others in one line."""
    from bitcomm.commands.env_train import SUPPORTED

    text = (ROOT / "docs" / "env_learning.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| learning flags |"))
    assert set(re.findall(r"--([\w-]+)", row)) == {name.replace("_", "-") for name in SUPPORTED}
