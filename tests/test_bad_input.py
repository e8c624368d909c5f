"""Every flag of every command fed bad values: exit status 2 and one stderr line that names the flag,
the value and what is allowed, before any work starts (each case takes milliseconds).

The cases are derived from the parsers (`bitcomm.cli.build_parser()`), so a new flag or command is
covered with no edit here: a flag's type picks its bad values (`BAD`), a text flag with a syntax of
its own lists them in `BAD_TEXT`, and `ALLOWED` documents each bad-looking value a flag legitimately
accepts (those are not run). `KNOWN` adds the cross-flag cases of issue 20.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import re
import signal
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from bitcomm.cli import build_parser, main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError

FILE, READONLY, DIRECTORY = "<an existing file>", "<in a read-only folder>", "<an existing folder>"
PIPE = "<a named pipe>"  # a device as well: written by renaming a file over it, /dev/null was replaced (as root)
BAD: dict[str, list[str]] = {
    "integer": ["-1", "0", "1000000000000", "abc", "2.5", "nan"],
    "number": ["-1", "0", "nan", "inf", "-inf", "1e300", "abc"],
    "out_dir": [FILE, READONLY, "", PIPE],
    "out_file": [DIRECTORY, READONLY, "", PIPE],
    "choice": ["nonsense"],
    "positional": ["no/such/run", FILE],
}
"""Bad values by kind of flag: `integer` and `number` are also the learning options' int and float."""

BAD_TEXT: dict[str, list[str]] = {
    "--observes": ["0,0", "5,0", "a,b", "1"],
    "--recipients": ["5;0", "0;1", "x", "1,1;0"],
    "--sizes": ["1000", "1", "abc", "", "10,-4"],
    "--stages": ["nonsense", "spread:0", "-5", "²", "spread:²", "16,16"],  # "²" is a digit to str.isdigit, not to int()
    "--techniques": ["nonsense", "", "improved-bitwise,improved-bitwise"],
    "--vary": ["nonsense", "lr=", "lr=inf", "lr=abc", "hidden=-8", "delay=300", "flip_prob=2"],
    "--param": ["nonsense", "delay=", "delay=300", "flip_prob=nan", "act_delay=abc", "delay=1.5"],
    "--onnx": ["no/such/file.onnx", FILE],
    "--address": ["nonsense", "host:0", "host:99999", "ray://", "127.0.0.1:6379"],  # the last: no --backend ray
    "--env": ["no_such_module_xyz:make", "json:nosuch", "json:JSONDecoder", "no-colon"],
    "--env-kwargs": ["[1]", "{bad"],
    "--topology": ["star", "[[1]]", "{"],
    "--fixed-actions": ["[1]", "{bad"],
}
"""Text flags with a syntax of their own (`--onnx` of deploy reads a file; export's writes one)."""

ALL = "*"
ALLOWED: dict[tuple[str, str], set[str]] = {
    # (command or *, flag) -> values that are legitimate, with why
    (ALL, "--seed"): {"0"},  # seed 0 is the default
    (ALL, "--eval-seed"): {"0"},
    ("compare", "--first-seed"): {"0"},  # the default: seeds 0..S-1
    (ALL, "--act-delay"): {"0"},  # moves take effect at once (the paper)
    (ALL, "--flip-prob"): {"0"},  # probabilities: 0 is a noiseless channel
    (ALL, "--drop-prob"): {"0"},
    (ALL, "--act-fail-prob"): {"0"},
    ("train", "--eval-episodes"): {"0"},  # 0: no final evaluation
    ("scaling", "--episodes"): {"0"},  # 0 skips training
    ("variance", "--fit-batches"): {"0"},  # 0: critics not fitted
    ("variance", "--plateau"): {"0"},  # 0: always fit every batch
    # learning options: 0 turns a loss term or trick off; a huge value is allowed where it means "never"/"all"
    (ALL, "--train-max-steps"): {"0", "1000000000000"},
    (ALL, "--anneal-episodes"): {"0", "1000000000000"},  # 0: the schedule follows the budget; huge: barely decays
    (ALL, "--move-decay-below"): {"0", "1e300"},  # 0: the decay from the first episode; huge: from the second batch
    (ALL, "--senders-wait-below"): {"0", "1e300"},  # 0: the senders at their `_from`; huge: from the second batch
    (ALL, "--greedy-senders"): {"0"},  # 0: off
    (ALL, "--critic-epochs"): {"0"},  # 0: the critics step in every epoch
    (ALL, "--greedy-senders-from"): {"0"},  # 0: from the first batch (the default recipe's greedy senders)
    (ALL, "--held-messages"): {"0"},  # 0: off
    (ALL, "--held-messages-from"): {"0"},  # 0: from the first batch
    (ALL, "--message-divergence-radius"): {"1000000000000"},  # beyond the grid: every pair of goals
    (ALL, "--staleness"): {"0"},  # 0: synchronous  # 0 or beyond max_steps: the task's own limit
    (ALL, "--keep-checkpoints"): {"1000000000000"},  # keep them all
    (ALL, "--held-out-every"): {"0", "1000000000000"},  # 0: never; huge: once, at the end
    (ALL, "--conv-stride"): {"1000000000000"},  # every layer down to one cell
    (ALL, "--checkpoint-seconds"): {"0", "1e300"},  # 0: every batch; huge: only at the end
    **{
        (ALL, f"--{name}"): {"0", "1e300"}
        for name in (
            "entropy-move",
            "entropy-message",
            "entropy-message-marginal",
            "message-divergence",
            "message-logit-decay",
            "sharpen-messages",
            "sharpen-moves",
            "uniform-move",
            "clip",
            "goal-coef",
            "seen-coef",
            "code-coef",
            "channel-noise",
            "max-grad-norm",
            "aux-coef",
        )
    },
    # a rate of 1e300 is refused: the optimizers step in float32, and a rate float32 cannot hold was a traceback
    # from inside Adam on the wrapped env (a huge rate it can hold is a choice, which the NaN guard stops)
}

RUN = "<a tiny trained run>"
REQUIRED: dict[str, list[str]] = {"eval": [RUN], "export": [RUN, "--onnx", "x.onnx"], "variance": [RUN]}
"""Arguments a command needs: a real run, so that task flags are checked against its task."""

KNOWN: list[tuple[list[str], str]] = [
    (["train", "--delay", "300"], "delay"),  # never arrives in a 256-step episode
    (["train", "--delay", "100"], "delay"),  # nor within the recipe's 64 training steps
    (["baseline", "--delay", "20", "--max-steps", "10"], "delay"),
    (["baseline", "--act-delay", "20", "--max-steps", "10"], "act_delay"),
    (["train", "--messages", "onehot", "--bits", "30"], "bits"),  # 2^30 one-hot words
    (["train", "--messages", "onehot", "--bits", "24", "--size", "4"], "bits"),
    (["train", "--num-envs", "100000000"], "num-envs"),
    (["train", "--num-envs", "2", "--minibatches", "3"], "minibatches"),  # typed: more minibatches than episodes
    (["train", "--hidden", "-8"], "hidden"),
    (["train", "--hidden", "100000000"], "hidden"),
    (["train", "--epochs", "100000000"], "epochs"),
    (["train", "--critic-epochs", "5"], "critic-epochs"),  # more passes of the critics than the recipe's 4 epochs
    (["train", "--lr", "inf"], "lr"),
    (["train", "--checkpoint-seconds", "-1"], "checkpoint-seconds"),
    (["train", "--checkpoint-seconds", "nan"], "checkpoint-seconds"),
    (["render", "--max-steps", "100000"], "max-steps"),  # one frame per step
    (["analyze", "--samples", "1000000000000"], "samples"),
    (["scaling", "--sizes", "1000"], "sizes"),
    (["deploy", "--deadline-ms", "inf"], "deadline-ms"),
    (["deploy", "--timeout", "nan"], "timeout"),
    (["deploy", "--timeout", "inf"], "timeout"),
    (["render", "--fps", "nan"], "fps"),
    (["render", "--out", "episode"], "out"),  # the animation is a GIF: a name without .gif was a PIL traceback
    (["render", "--fps", "1e-300"], "fps"),  # a frame of 10^300 s: a PIL OverflowError (at most 655 s in a GIF)
    (["sweep", "--param", "delay=nan"], "delay"),  # int(nan) of a whole-number parameter: a traceback
    (["sweep", "--param", "act_delay=1,inf"], "act_delay"),
    (["baseline", "--seed", "-1"], "seed"),
    (["baseline", "--size", "100000"], "size"),
    (["baseline", "--bits", "4"], "bits"),  # the oracle needs 7 bits on a 10x10 grid
    (["compare", "--vary", "lr=1e-3,1e-3"], "vary"),
    (["compare", "--seeds", "5", "--eval-seed", "3"], "eval-seed"),
]


def kind(action: argparse.Action) -> str | None:
    """Which list of `BAD` applies, "text" for `BAD_TEXT`, None for a flag that takes no value."""
    if action.nargs == 0 or isinstance(action, argparse.BooleanOptionalAction):
        return None
    if not action.option_strings:
        return "positional"
    name = getattr(action.type, "__name__", "")
    if action.choices is not None or name == "str":  # a learning option of text is a choice of its config's
        return "choice"
    if action.type is int or name in ("integer", "int"):
        return "integer"
    if action.type is float or name in ("number", "float"):
        return "number"
    if name in ("out_dir", "out_file"):
        return name
    if name == "gif_file":  # an out_file with a suffix
        return "out_file"
    return "text"


def subparsers() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def cases() -> Iterator[tuple[str, str, str]]:
    """(command, flag, value) for every flag of every command and each bad value that applies."""
    for command, parser in subparsers().items():
        for action in parser._actions:
            k = kind(action)
            if k is None:
                continue
            flag = action.option_strings[-1] if action.option_strings else action.metavar or action.dest
            values = BAD_TEXT.get(flag) if k == "text" or (flag == "--onnx" and command == "deploy") else BAD[k]
            assert values is not None, f"{command} {flag}: a text flag needs its bad values in BAD_TEXT"
            allowed = ALLOWED.get((command, flag), set()) | ALLOWED.get((ALL, flag), set())
            for value in values:
                if value not in allowed:
                    yield command, str(flag), value


CASES = list(cases())


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> str:
    out = tmp_path_factory.mktemp("bad_input") / "run"
    argv = ["train", "--size", "4", "--bits", "4", "--max-steps", "16", "--num-envs", "16", "--episodes", "16"]
    assert main([*argv, "--quiet", "--eval-episodes", "0", "--threads", "1", "--out", str(out)]) == 0
    return str(out)


@pytest.fixture
def places(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, tiny_run: str) -> Iterator[dict[str, str]]:
    """A file, a folder, a read-only folder and a run; the cwd is tmp_path, so a default --out lands there."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file.txt").write_text("not a folder, not a checkpoint\n")
    (tmp_path / "folder").mkdir()
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    os.mkfifo(tmp_path / "pipe.gif")  # named as render's --out must be
    yield {FILE: "file.txt", DIRECTORY: "folder", READONLY: "locked/out", PIPE: "pipe.gif", RUN: tiny_run}
    locked.chmod(stat.S_IRWXU)


class TookTooLong(Exception):
    """Raised by the alarm: the command started work instead of refusing."""


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str], seconds: int = 30) -> tuple[int, list[str]]:
    """`bitcomm.cli.main(argv)` in this process: its exit status and stderr lines (the alarm stops work)."""

    def alarm(*_: object) -> None:
        raise TookTooLong(f"{argv} ran past {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else 1
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    return code, capsys.readouterr().err.strip().splitlines()


def names(line: str, flag: str, value: str) -> bool:
    """The line names the flag (a positional by what it holds; `--vary`/`--param` by the option varied)."""
    forms = {flag.lstrip("-"), flag.lstrip("-").replace("-", "_")}
    if not flag.startswith("--"):
        forms |= {"RUN", "checkpoint"}
    if flag in ("--vary", "--param"):
        forms.add(value.partition("=")[0])
    return any(form and form in line for form in forms)


def says_allowed(line: str) -> bool:
    """After the value comes what is wrong with it or what is allowed: `invalid NAME=VALUE: REASON`."""
    return re.search(r"invalid .+: \S", line) is not None


@pytest.mark.parametrize(("command", "flag", "value"), CASES, ids=[" ".join(c) for c in CASES])
def test_flag_refuses_bad_value(
    command: str, flag: str, value: str, places: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    text = places.get(value, value)
    required = REQUIRED.get(command, [])
    positional = not flag.startswith("--")
    required = [places.get(r, r) for r in required]
    # --flag=VALUE: argparse reads a lone "-inf" as a flag of its own ("expected one argument")
    argv = [command, text, *required[1:]] if positional else [command, *required, f"{flag}={text}"]
    code, lines = run_cli(argv, capsys)
    assert code == 2, (argv, lines)
    assert len(lines) == 1, (argv, lines)
    assert names(lines[0], flag, text) and says_allowed(lines[0]), (argv, lines)
    assert "Traceback" not in lines[0]


@pytest.mark.parametrize(("argv", "flag"), KNOWN, ids=[" ".join(a) for a, _ in KNOWN])
def test_known_bad_inputs_refused(
    argv: list[str], flag: str, places: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    code, lines = run_cli(argv, capsys)
    assert code == 2 and len(lines) == 1, (argv, lines)
    assert names(lines[0], flag, "") and says_allowed(lines[0]), (argv, lines)


def test_every_command_and_flag_is_covered() -> None:
    """Each command has cases, and every flag that takes a value has at least one bad value tried."""
    parsers = subparsers()
    covered = {(c, f) for c, f, _ in CASES}
    for command, parser in parsers.items():
        for action in parser._actions:
            if kind(action) is None:
                continue
            flag = action.option_strings[-1] if action.option_strings else action.metavar or action.dest
            assert (command, str(flag)) in covered, f"{command} {flag}: every bad value is ALLOWED?"
    assert len(CASES) > 500


def test_every_flag_has_help_and_a_default_shown() -> None:
    """Each flag's own help names its default, 0 too (a switch, default False, and a flag without one, None, need
    not)."""
    for command, parser in subparsers().items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.option_strings or action.dest == "help":
                continue
            assert action.help, f"{command} {action.option_strings[0]} has no help text"
            shown = "default" in formatter._get_help_string(action).lower()
            assert shown or action.default is None or action.default is False, f"{command} {action.option_strings[0]}"


def test_help_is_fast_and_imports_no_torch() -> None:
    """`bitcomm --help` builds every parser: that must not import torch (2 s) and must take < 0.5 s of CPU (the
    process's own time, which other processes sharing the machine do not inflate as they do wall time)."""
    code = "import sys, time; t = time.process_time(); import bitcomm.cli; bitcomm.cli.build_parser(); "
    code += "print(time.process_time() - t, 'torch' in sys.modules)"
    best = math.inf
    for _ in range(3):  # the best of three: disk caches warm up
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=os.environ)
        seconds, torch_loaded = out.stdout.split()
        assert torch_loaded == "False"
        best = min(best, float(seconds))
    assert best < 0.5, f"building the parsers took {best:.2f} s"


def test_eval_batch_matches_the_evaluator() -> None:
    from bitcomm.commands.flags import EVAL_BATCH
    from bitcomm.policies.evaluation import EVAL_CHUNK

    assert EVAL_BATCH == EVAL_CHUNK


def _answer(moves: object = 0, bits: object = 0, n: int = 2, K: int = 4):  # type: ignore[no-untyped-def]
    """A policy of one's own that answers every episode with these moves and bits (a shape of its own where given)."""
    import numpy as np

    def policy(obs):  # type: ignore[no-untyped-def]
        B = obs.planes.shape[0]
        return np.full((B, n), moves), np.full((B, n, K), bits)

    return policy


@pytest.mark.parametrize(
    ("policy", "line"),
    [
        (_answer(moves=-1), "invalid policy move=-1: every move must be 0 to 4"),  # was the last move, silently
        (_answer(moves=1.5), "invalid policy move=1.5"),  # was move 1, silently
        (_answer(bits=2), "invalid policy bit=2: every bit must be 0 or 1"),  # was a 1, silently
        (_answer(moves=7), "invalid policy move=7"),  # was numpy's IndexError
        (_answer(K=3), r"invalid policy output shapes moves=\(10, 2\), bits=\(10, 2, 3\): expected"),
        (lambda obs: None, "invalid policy output='NoneType': must be a \\(moves, bits\\) pair"),
    ],
)
def test_a_policy_of_ones_own_that_answers_what_the_env_cannot_take_is_one_line(policy, line: str) -> None:
    from bitcomm.policies.evaluation import evaluate

    task = TaskConfig(EnvConfig(size=3), ChannelConfig(bits=4))
    with pytest.raises(ConfigError, match=line):
        evaluate(policy, task, episodes=10)
    assert evaluate(_answer(moves=1.0, bits=True), task, episodes=10).episodes == 10  # integral floats, bools: taken


@pytest.mark.parametrize(
    ("env", "channel", "line"),
    [
        ({"size": 4}, {"bits": 4}, "invalid task size=4: the policy was trained with size=3"),
        ({"size": 3}, {"bits": 5}, "invalid task bits=5: the policy was trained with bits=4"),
        ({"size": 3, "n_agents": 3}, {"bits": 4, "recipients": [[1, 2], [0], [0]]}, "invalid task slots=2"),
    ],
)
def test_a_controller_evaluated_on_a_task_its_inputs_do_not_fit_names_the_task(env, channel, line: str) -> None:
    """It was `invalid input shapes planes=(20, 2, 4, 4)`: the shapes of a batch, naming neither task."""
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.networks import ModelConfig, PolicyNet

    controller = Controller(PolicyNet(TaskConfig(EnvConfig(size=3), ChannelConfig(bits=4)), ModelConfig()), {})
    with pytest.raises(ConfigError, match=line):
        evaluate(controller, TaskConfig(EnvConfig(**env), ChannelConfig(**channel)), episodes=10)
    played = TaskConfig(EnvConfig(size=3, n_agents=3), ChannelConfig(bits=4, flip_prob=0.1))  # inputs that fit
    assert evaluate(controller, played, episodes=10).episodes == 10


@pytest.mark.parametrize(("bits", "used_mib"), [(16, 854), (18, 2200)])
def test_training_with_one_hot_messages_is_refused_where_it_would_not_fit_and_only_there(
    bits: int, used_mib: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Peak memory of `bitcomm train --messages onehot --bits K --episodes 384 --threads 1` (10x10, 3 batches,
    session 55): 854 MiB at 16 bits, 2,200 at 18. The check counted 348 / 1,308 MiB for what a 392 MiB 4-bit run
    does not hold, left the tables a batch acts on out, and so let a run start on memory it would run out of."""
    from bitcomm.commands import flags
    from bitcomm.learn.config import make_train_config

    cfg = make_train_config("reinforced", TaskConfig(EnvConfig(), ChannelConfig(bits=bits)), messages="onehot")
    monkeypatch.setattr(flags, "available_bytes", lambda: used_mib << 20)
    flags.check_train(cfg)  # it fits: not refused
    monkeypatch.setattr(flags, "available_bytes", lambda: (used_mib - 392) * 9 // 10 << 20)
    with pytest.raises(ConfigError, match=f"invalid bits={bits}: one-hot messages over 2\\^{bits} words"):
        flags.check_train(cfg)


def test_the_memory_refusal_says_how_many_runs_and_workers_its_figure_counts(monkeypatch: pytest.MonkeyPatch) -> None:
    """`bitcomm compare --jobs 2` checks two runs' memory at once and an A3C run one learner per worker: the line
    gave a figure twice or four times one run's without saying so."""
    from bitcomm.commands import flags
    from bitcomm.learn.config import make_train_config

    cfg = make_train_config("reinforced", TaskConfig(EnvConfig(), ChannelConfig()))
    a3c = make_train_config("reinforced", TaskConfig(EnvConfig(), ChannelConfig()), mode="a3c", workers=4)
    monkeypatch.setattr(flags, "available_bytes", lambda: 1 << 10)
    for config, processes, counted in ((cfg, 1, "1 run(s) at once"), (cfg, 2, "2 run(s) at once"),
                                       (a3c, 2, "2 run(s) at once, 4 workers each")):  # fmt: skip
        with pytest.raises(ConfigError, match=f"invalid size=10: the networks \\(hidden 128; {re.escape(counted)}\\)"):
            flags.check_train(config, processes)


def test_networks_too_large_for_their_grid_are_refused_naming_the_size(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--size 1000` was refused as `invalid hidden=128: the networks: ...`: what made them huge is the million cells
    their first layers read, not their width, which stays the one named where it is what outgrows memory."""
    from bitcomm.commands import flags

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(flags, "available_bytes", lambda: 8 << 30)
    for argv, runs in ((["train", "--size", "1000"], 1), (["compare", "--vary", "size=1000"], 2)):
        code, lines = run_cli(argv, capsys)
        said = f"invalid size=1000: the networks (hidden 128; {runs} run(s) at once), whose first layers read every "
        assert code == 2 and len(lines) == 1, (argv, lines)
        assert said in lines[0] and lines[0].endswith("GB available; give a smaller grid"), lines
    code, lines = run_cli(["train", "--hidden", "100000"], capsys)
    said = "bitcomm train: error: invalid hidden=100000: the networks (1 run(s) at once): "
    assert code == 2 and lines[-1].startswith(said), lines
    assert list(tmp_path.iterdir()) == []  # refused before a folder is made


def test_training_that_evaluates_held_out_episodes_counts_their_one_hot_tables(monkeypatch: pytest.MonkeyPatch) -> None:
    """`--held-out-every N` plays `held_out_episodes` (1,000) side by side between batches, beside the 2^K-wide
    parameters and a copy of the policy: at 16 bits, 2 MB of one-hot tables per episode, 2 GB for the evaluation
    against 0.3 GB for a batch of 128. The check counted the training batch alone and let such a run start."""
    from bitcomm.commands import flags
    from bitcomm.learn.config import make_train_config

    task = TaskConfig(EnvConfig(), ChannelConfig(bits=16))
    plain = make_train_config("reinforced", task, messages="onehot")
    monkeypatch.setattr(flags, "available_bytes", lambda: 2 * flags.onehot_bytes(plain) + (1 << 30))
    flags.check_train(plain)  # the training alone fits
    held = make_train_config("reinforced", task, messages="onehot", held_out_every=1024)
    with pytest.raises(ConfigError, match=r"invalid held-out-episodes=1000: 1000 episodes side by side on this task "
                       r"with one-hot messages over 2\^16 words, beside the 2\^16-wide parameters"):  # fmt: skip
        flags.check_train(held)
    flags.check_train(dataclasses.replace(held, held_out_episodes=100))  # 0.2 GB of tables: it fits


def test_a_one_hot_policy_too_wide_to_play_that_many_episodes_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A one-hot policy acts on tables of 2^K per agent and episode (logits, softmax, cumulative sum, heard
    slots): an evaluation of 4,096 episodes at 18 bits ran out of memory on 34 GB with a traceback, and a
    training run's final evaluation only after the training. Every command that plays one counts them first."""
    from bitcomm.commands import flags

    run = str(tmp_path / "onehot")
    argv = ["train", "--size", "4", "--bits", "10", "--messages", "onehot", "--max-steps", "16", "--num-envs", "16"]
    assert main([*argv, "--episodes", "16", "--quiet", "--eval-episodes", "0", "--threads", "1", "--out", run]) == 0
    task = TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=10))
    need = flags.play_bytes(task, 4096, onehot=True)
    assert need > 20 * flags.play_bytes(task, 4096)  # 134 MB of one-hot tables, 5 MB of planes
    monkeypatch.setattr(flags, "available_bytes", lambda: need // 2)
    refused = [
        (["eval", run, "--episodes", "4096"], "episodes"),
        (["sweep", run, "--param", "delay=1", "--episodes", "4096", "--out", str(tmp_path / "s")], "episodes"),
        (["analyze", run, "--envs", "4096", "--out", str(tmp_path / "a")], "envs"),
        (["deploy", run, "--episodes", "4096"], "episodes"),
        ([*argv, "--episodes", "16", "--eval-episodes", "4096", "--out", str(tmp_path / "t")], "eval-episodes"),
    ]
    for command, flag in refused:
        code, lines = run_cli(command, capsys)
        assert code == 2 and len(lines) == 1, (command, lines)
        assert f"invalid {flag}=4096" in lines[0] and "one-hot messages over 2^10 words" in lines[0], lines
    assert not (tmp_path / "t").exists()  # refused before training


def test_a_small_batch_takes_the_recipes_minibatches_down_with_it() -> None:
    """`train --num-envs 2` was refused as `invalid minibatches=4`, a flag the user never typed: the recipe's 4
    minibatches follow a batch of fewer episodes (a typed `--minibatches` above it is still refused, above)."""
    from bitcomm.cli import build_parser
    from bitcomm.commands.env_train import env_config_from_args
    from bitcomm.learn.config import make_train_config

    assert make_train_config("reinforced", num_envs=2).minibatches == 2
    assert make_train_config("reinforced", num_envs=64).minibatches == 4
    assert make_train_config("reinforced", num_envs=2, minibatches=1).minibatches == 1
    args = build_parser().parse_args(
        ["train", "--env", "mpe2.simple_speaker_listener_v4:parallel_env", "--num-envs", "2"]
    )
    assert env_config_from_args(args).minibatches == 2


@pytest.mark.parametrize("command", ["eval", "render", "analyze", "sweep", "variance", "deploy", "baseline", "train"])
def test_the_help_of_a_command_that_plays_a_run_says_a_run_plays_its_own_task(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`eval --help` gave `--size (default 10)`, `--bits (default 7)`, ... while `eval RUN` plays the run's own task
    where no flag is typed (a 4x4 run plays 4x4): the commands that read a run say so above their task flags."""
    from bitcomm.commands.common import RUN_TASK

    with contextlib.suppress(SystemExit):  # argparse's exit after help, which main takes for some commands
        main([command, "--help"])
    said = " ".join(capsys.readouterr().out.split())
    assert (" ".join(RUN_TASK.split()) in said) is (command not in ("baseline", "train"))
