"""A run folder that cannot be corrupted: one writer at a time (the lock names its holder's pid, a dead
holder blocks nothing), nothing non-finite checkpointed, every weight and state file checksummed,
`latest.json` confined to its folder, what a kill leaves removed on start and resume, and checkpoint
retention (the last N and the best). Errors are one line with exit status 2 from the real CLI."""

from __future__ import annotations

import csv
import errno
import json
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import torch

from bitcomm.checkpoint import (
    Diverged,
    checkpoints,
    clean,
    load_state,
    load_weights,
    rank,
    read_config,
    resolve,
    rolling_length,
    save_checkpoint,
)
from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.learn.config import make_train_config
from bitcomm.learn.learner import Learner
from bitcomm.learn.run_folder import (
    RESUMES,
    budget_note,
    kept_budget,
    learner_state,
    machine_label,
    pointed_at,
    restore_learner,
    run_machines,
)
from bitcomm.provenance import machine
from bitcomm.run_lock import LOCK, run_lock

TASK = ["--size", "4", "--bits", "4", "--max-steps", "16", "--num-envs", "16"]
QUICK = [*TASK, "--threads", "1", "--quiet", "--eval-episodes", "0", "--checkpoint-seconds", "0"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
HOLD = """import sys, time
from bitcomm.run_lock import run_lock
with run_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(120)
"""
"""A process that holds a run folder's lock until it is killed."""


def cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    try:
        rc = main(list(argv))
    except SystemExit as e:  # argparse
        rc = int(e.code or 0)
    return rc, capsys.readouterr().err


def refused(capsys: pytest.CaptureFixture[str], *argv: str, naming: str) -> str:
    """Run the CLI; assert exit status 2 and one stderr line that contains `naming`."""
    rc, err = cli(capsys, *argv)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert naming in lines[0], lines[0]
    return lines[0]


def tiny_config(**kw):
    from bitcomm.learn.config import make_train_config

    task = TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=4))
    return make_train_config(task=task, **{"num_envs": 16, "episodes": 48, "checkpoint_seconds": 0.0, **kw})


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished run of 3 batches, a checkpoint after each; tests tamper with copies of it."""
    from bitcomm.learn.run import train

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("trained") / "run"
    train(tiny_config(), out, progress=False)
    return out


@pytest.fixture
def run(trained: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(trained, tmp_path / "run"))


def leftovers(run: Path) -> list[str]:
    """Temporary files and checkpoint files without their pair."""
    names = [p.name for p in (run / "checkpoints").iterdir()] + [p.name for p in run.iterdir()]
    tmp = [n for n in names if ".tmp" in n]
    stems = {n.split(".")[0] for n in names if n.startswith("ckpt_")}
    unpaired = [s for s in stems if not {f"{s}.safetensors", f"{s}.state.pt"} <= set(names)]
    return tmp + unpaired


# ---------------------------------------------------------------------------------------------- starts
@pytest.mark.parametrize("mine", ["config.json", "metrics.csv", "learning_curve.png"])
def test_a_fresh_run_leaves_alone_a_folder_whose_files_are_not_a_runs(mine: str, tmp_path: Path, capsys) -> None:
    """A fresh run overwrites config.json, metrics.csv and the curves: in a folder that is not a run's, one line and
    nothing written (not even the lock)."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / mine).write_text("the user's own\n")
    (folder / "notes.txt").write_text("notes\n")
    refused(capsys, "train", *QUICK, "--episodes", "16", "--out", str(folder), naming=mine)
    assert sorted(p.name for p in folder.iterdir()) == sorted([mine, "notes.txt"])
    assert (folder / mine).read_text() == "the user's own\n"


def test_a_run_stopped_before_its_first_checkpoint_is_trained_again_not_resumed(run: Path, capsys) -> None:
    """Its config.json and metrics.csv are a run's, so a fresh start may replace them; a resume says why it cannot."""
    shutil.rmtree(run / "checkpoints")
    line = refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", naming=str(run))
    assert "before its first checkpoint" in line and "without --resume" in line
    rc, err = cli(capsys, "train", *QUICK, "--out", str(run), "--episodes", "16")
    assert rc == 0, err
    assert checkpoints(run)[-1][0] == 16
    assert {tuple(s for s, _ in steps) for steps in tensorboard_scalars(run).values()} == {(16,)}  # the old run's gone


def test_a_run_without_a_checkpoint_yet_is_called_a_run_by_the_commands_that_read_one(run: Path, capsys) -> None:
    """variance, eval and render said "(not a bitcomm run)" of a run stopped before its first checkpoint (or still
    playing toward it); and variance said so of a path that does not exist, where eval says there is no such one."""
    shutil.rmtree(run / "checkpoints")
    for command in ("variance", "eval", "render"):
        line = refused(capsys, command, str(run), naming="a run with no checkpoint yet")
        assert "not a bitcomm run" not in line and "--checkpoint-seconds" in line
        refused(capsys, command, str(run / "nothing"), naming="no such file or run folder")


def test_a_resume_of_a_run_that_lost_its_latest_json_says_how_to_restore_it(run: Path, capsys) -> None:
    """Not "train it again without --resume", which would remove its checkpoints: the line names the last one and
    the latest.json that resumes from it."""
    episodes, last = checkpoints(run)[-1]
    (run / "checkpoints" / "latest.json").unlink()
    argv = ["train", *QUICK, "--out", str(run), "--resume", "--episodes", str(episodes + 16)]
    line = refused(capsys, *argv, naming=last.name)
    assert "without --resume" not in line
    (run / "checkpoints" / "latest.json").write_text(line.split(" as ", 1)[1])
    rc, err = cli(capsys, *argv)
    assert rc == 0, err
    assert checkpoints(run)[-1][0] == episodes + 16


def test_a_resume_of_checkpoints_copied_without_their_run_folder_says_to_copy_the_whole_folder(
    run: Path, tmp_path: Path, capsys
) -> None:
    """It was "unreadable (FileNotFoundError ...)": the line now says what else to bring, and what reads checkpoints/
    alone does."""
    copied = tmp_path / "copied"
    shutil.copytree(run / "checkpoints", copied / "checkpoints")
    episodes = checkpoints(run)[-1][0]
    argv = ["train", *QUICK, "--out", str(copied), "--resume", "--episodes", str(episodes + 16)]
    line = refused(capsys, *argv, naming="config.json': missing")
    assert "copy the whole run folder" in line
    assert main(["eval", str(copied), "--episodes", "10"]) == 0


def test_a_resume_of_a_run_still_before_its_first_checkpoint_names_its_writer(run: Path, capsys) -> None:
    """Not "train it again without --resume": that run is still playing, in the process holding the lock."""
    shutil.rmtree(run / "checkpoints")
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(run)], stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        line = refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", naming=str(run))
        assert f"pid {holder.pid}" in line and "another process" in line
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()


def test_a_fresh_start_on_a_run_still_being_written_is_one_line_naming_its_writer(run: Path, capsys) -> None:
    """The second `bitcomm train` on an --out being trained printed `run folder: ...` on stdout before the lock's
    line (before its first checkpoint), or said "use --resume" (after it): one line naming the pid, nothing else."""
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(run)], stdout=subprocess.PIPE, text=True, env=ENV)
    line = (
        f"bitcomm train: error: invalid out={str(run)!r}: another process (pid {holder.pid}) is writing this run "
        "folder; let it end or use another --out"
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        for before_first_checkpoint in (False, True):
            if before_first_checkpoint:
                shutil.rmtree(run / "checkpoints")
            rc = main(["train", *QUICK, "--out", str(run), "--episodes", "64"])
            out, err = capsys.readouterr()
            assert rc == 2 and out == "" and err.strip().splitlines() == [line], (out, err)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()


@pytest.mark.parametrize(
    "changed",
    [
        ["--size", "5"],
        ["--flip-prob", "0.1"],
        ["--observes", "0,1"],  # (an agent may not observe itself: still one line)
        ["--lr", "0.1"],
        ["--mode", "a3c"],
        ["--estimator", "standard"],
        ["--messages", "onehot"],
        ["--recipe", "paper"],
        ["--seed", "3"],
    ],
)
def test_a_resume_refuses_a_flag_that_would_change_the_run(changed: list[str], run: Path, capsys) -> None:
    """A resume continues the run as it started: a flag typed with another value is one line, not ignored."""
    before = (run / "checkpoints" / "latest.json").read_text()
    refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", *changed, naming=changed[0][2:])
    assert (run / "checkpoints" / "latest.json").read_text() == before


def test_a_resume_takes_the_budget_and_how_often_it_saves_and_the_flags_it_was_trained_with(run: Path, capsys) -> None:
    """The flags the run was started with, typed again (the ring typed as its map), are accepted."""
    same = ["--estimator", "improved", "--messages", "bitwise", "--recipe", "reinforced", "--seed", "0"]
    same += ["--observes", "1,0", "--recipients", "1;0", "--keep-checkpoints", "1"]
    rc, err = cli(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", *same)
    assert rc == 0, err
    assert json.loads((run / "config.json").read_text())["keep_checkpoints"] == 1
    kept = [e for e, _ in checkpoints(run)]
    assert kept[-1] == 64 and len(kept) <= 2  # the last one and the best


def test_a_resume_from_python_with_another_config_is_one_line_naming_the_option(run: Path) -> None:
    """`train(cfg, out, resume=True)` continues the run as it started, as `bitcomm train --resume` does: a config that
    would change what it learns is refused in one line naming the option, where the run went on under the new seed or
    learning rate and recorded it as the whole run's. The budget and how often it saves may change."""
    from bitcomm.learn.run import train

    before = sorted(p.name for p in (run / "checkpoints").iterdir())
    other_task = TaskConfig(EnvConfig(size=5, max_steps=16), ChannelConfig(bits=5))
    for cfg, line in (
        (tiny_config(episodes=64, seed=9), "invalid seed=9: the run in .* was trained with seed=0, and a resume"),
        (tiny_config(episodes=64, lr=0.1), "invalid lr=0.1: .* was trained with lr=0.003"),
        (tiny_config(episodes=64, num_envs=32), "invalid num_envs=32: .* was trained with num_envs=16"),
        (
            make_train_config(task=other_task, num_envs=16, episodes=64),
            "invalid task.env.size=5: .* with task.env.size=4",
        ),
    ):
        with pytest.raises(ConfigError, match=line):
            train(cfg, run, resume=True, progress=False)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == before
    resumed = train(
        tiny_config(episodes=64, checkpoint_seconds=30.0, keep_checkpoints=1), run, resume=True, progress=False
    )
    assert resumed.name == "ckpt_000000064.safetensors"


def test_a_resume_at_or_past_its_budget_says_it_has_nothing_to_train(run: Path, capsys) -> None:
    """`make train` run again resumes a finished run: it trains nothing, and says so rather than looking stuck. A
    budget below what was played keeps the run's own in config.json and the checkpoint, where the resume that trained
    nothing recorded the smaller figure as the run's budget."""
    for budget, stays in (("48", ""), ("32", " (its budget stays 48)")):
        assert main(["train", *QUICK, "--out", str(run), "--resume", "--episodes", budget]) == 0
        line = f"already played 48 episodes of --episodes {budget}; nothing to train{stays}\n"
        assert line in capsys.readouterr().out
        assert json.loads((run / "config.json").read_text())["episodes"] == 48
        assert read_config(run)["episodes"] == 48
    assert checkpoints(run)[-1][0] == 48


@pytest.mark.parametrize(
    ("asked", "played", "recorded", "kept"),
    [
        (300, 200, 200, 300),  # a larger budget: trains on to it
        (200, 200, 200, 200),  # `make train` again
        (100, 200, 200, 200),  # less than played: the run's budget stays
        (100, 120, 200, 120),  # a run stopped short of its budget: what it played
        (150000, 200064, 200000, 200000),  # a batch past its budget (a3c): the budget, not the overshoot
        (200000, 200064, 200000, 200000),
    ],
)
def test_the_budget_a_resume_records(asked: int, played: int, recorded: int, kept: int) -> None:
    assert kept_budget(asked, played, recorded) == kept


@pytest.mark.parametrize(
    ("asked", "kept", "recorded", "note"),
    [
        (48, 48, 48, ""),
        (32, 48, 48, " (its budget stays 48)"),
        (500, 896, 200000, " (its budget is now 896, the episodes played, not 200,000)"),  # a run stopped short
    ],
)
def test_a_resume_that_trains_nothing_says_what_budget_it_records(
    asked: int, kept: int, recorded: int, note: str
) -> None:
    """A run stopped at 896 of 200,000 episodes, resumed with --episodes 500, was told its budget "stays 896"."""
    assert budget_note(asked, kept, recorded) == note


def test_eval_refuses_a_task_whose_agents_hear_another_number_of_senders() -> None:
    """The senders an agent hears are its network's message inputs: another count is one line naming the flag."""
    import argparse

    from bitcomm.policies.source import POLICY_INPUTS, resolve_task

    base = TaskConfig(EnvConfig(size=4, n_agents=3), ChannelConfig(bits=4, recipients=((1, 2), (0, 2), (0, 1))))
    args = argparse.Namespace(recipients=((1,), (2,), (0,)))
    with pytest.raises(ConfigError, match=r"invalid recipients=.*trained to hear 2 sender\(s\) per agent"):
        resolve_task(args, base, fixed=POLICY_INPUTS)
    assert resolve_task(args, base).slots == 1  # a resume or a command that does not load the network may


def test_one_network_acts_for_any_number_of_agents_but_the_critics_see_how_many(run: Path, capsys) -> None:
    """A 2-agent policy plays a ring of 3 (each agent hears one sender, as in training): `eval` and the commands that
    act take `--agents 3`; `variance`, whose critics see every agent, refuses it in one line."""
    assert main(["eval", str(run), "--agents", "3", "--episodes", "20", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 20
    rc, _ = cli(capsys, "render", str(run), "--agents", "3", "--out", str(run / "three.gif"), "--seed", "1")
    assert rc == 0 and (run / "three.gif").stat().st_size > 0
    refused(capsys, "variance", str(run), "--agents", "3", naming="invalid agents=3: checkpoint")
    refused(capsys, "eval", str(run), "--size", "5", naming="invalid size=5: RUN")


@pytest.mark.parametrize("mode", ["sync", "a3c"])
def test_training_leaves_the_callers_torch_generator_as_it_was(mode: str, tmp_path: Path) -> None:
    """A notebook's own draws after `train` are those it would have made without it (the run seeds torch)."""
    from bitcomm.learn.run import train

    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    train(tiny_config(mode=mode, workers=1), tmp_path / "run", progress=False)
    assert torch.equal(torch.rand(3), expected)


def test_loading_a_run_leaves_the_callers_torch_generator_as_it_was(trained: Path) -> None:
    """`Controller.load` built its network's random initial weights from torch's global generator before reading
    the trained ones over them: a notebook's draws after it depended on whether it had loaded a policy."""
    from bitcomm.policies.controller import Controller

    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    Controller.load(trained)
    assert torch.equal(torch.rand(3), expected)


# ---------------------------------------------------------------------------------------------- lock
def test_a_second_writer_is_refused_with_the_holders_pid(run: Path, tmp_path: Path, capsys) -> None:
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    holders = [
        subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True, env=ENV)
        for folder in (run, fresh)
    ]
    try:
        for h in holders:
            assert h.stdout is not None and h.stdout.readline().strip() == "locked"
        before = (run / "checkpoints" / "latest.json").read_text()
        line = refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", naming=str(run))
        assert f"pid {holders[0].pid}" in line and "another process" in line
        line = refused(capsys, "train", *QUICK, "--episodes", "16", "--out", str(fresh), naming=f"pid {holders[1].pid}")
        assert (run / "checkpoints" / "latest.json").read_text() == before
        assert list(fresh.iterdir()) == [fresh / LOCK]
    finally:
        for h in holders:
            h.send_signal(signal.SIGKILL)
            h.wait()
    # the killed holder's lock file stays, naming a dead pid, and blocks nothing
    assert (fresh / LOCK).read_text().strip() == str(holders[1].pid)
    rc, err = cli(capsys, "train", *QUICK, "--episodes", "16", "--out", str(fresh))
    assert rc == 0, err
    assert checkpoints(fresh)[-1][0] == 16


def test_the_lock_is_reentrant_in_one_process_and_released(tmp_path: Path) -> None:
    with run_lock(tmp_path), run_lock(tmp_path):
        assert (tmp_path / LOCK).read_text().strip() == str(os.getpid())
    with run_lock(tmp_path):  # released: it can be taken again
        pass
    with pytest.raises(ConfigError, match="lock file"):
        with run_lock(tmp_path / "missing"):
            pass


def test_a_reader_of_a_run_still_training_reads_the_checkpoint_it_names_now(
    run: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`bitcomm eval RUN` while RUN trains: the checkpoint latest.json named can be pruned before it is opened (the
    run saved --keep-checkpoints newer ones meanwhile); the reader takes the one named now, not a damaged file."""
    import bitcomm.checkpoint

    real, calls = bitcomm.checkpoint.resolve, []

    def resolve_then_prune(path: Path | str) -> Path:
        file = real(path)
        if not calls:  # the run moves on to 64 episodes and prunes 48 before this reader opens it
            folder = file.parent
            for suffix in ("safetensors", "state.pt"):
                shutil.copy(folder / f"ckpt_000000048.{suffix}", folder / f"ckpt_000000064.{suffix}")
            latest = json.loads((folder / "latest.json").read_text())
            latest.update(checkpoint="ckpt_000000064.safetensors", state="ckpt_000000064.state.pt", episodes=64)
            (folder / "latest.json").write_text(json.dumps(latest))
            for suffix in ("safetensors", "state.pt"):
                (folder / f"ckpt_000000048.{suffix}").unlink()
        calls.append(file)
        return file

    monkeypatch.setattr(bitcomm.checkpoint, "resolve", resolve_then_prune)
    _, info = load_weights(run)
    assert [f.name for f in calls] == ["ckpt_000000048.safetensors", "ckpt_000000064.safetensors"]
    assert info["path"].endswith("ckpt_000000064.safetensors")
    with pytest.raises(ConfigError, match="no such file"):  # a file named outright is read or refused, not sought
        load_weights(run / "checkpoints" / "ckpt_000000048.safetensors")


# ---------------------------------------------------------------------------------------------- full disk
def _full_on_call(n: int, call: Any) -> Any:
    """`call`, but its `n`-th call fails as a full disk does: an OSError naming no file (a buffered write's)."""
    calls = []

    def fail(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == n:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return call(*args, **kwargs)

    return fail


class _FlushFails:
    """metrics.csv's file, whose third flush meets a full disk."""

    def __init__(self, file: Any) -> None:
        self.file, self.flush = file, _full_on_call(3, file.flush)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.file, name)


def _fill_the_disk(what: str, monkeypatch: pytest.MonkeyPatch) -> str:
    """Make a write of `what` after the first checkpoint fail as on a full disk; returns the file the error line
    names."""
    import bitcomm.checkpoint
    from bitcomm.learn.run_folder import Logger

    if what == "checkpoint":  # the third checkpoint's resume state: its first file
        monkeypatch.setattr(bitcomm.checkpoint, "_torch_save", _full_on_call(3, bitcomm.checkpoint._torch_save))
        return "ckpt_000000048.state.pt"
    if what == "metrics.csv":
        init = Logger.__init__

        def logger(self: Logger, *args: Any) -> None:
            init(self, *args)
            self.file = _FlushFails(self.file)

        monkeypatch.setattr(Logger, "__init__", logger)
        return "metrics.csv"
    if what == "tensorboard":  # written on TensorBoard's own thread, which the main thread hears of later
        from tensorboard.summary.writer.record_writer import RecordWriter

        # a write of the third batch's scalars (a header, then 11 a batch here): the main thread may hear of a
        # failed write only a batch or two after it, and by then it must have a checkpoint to name
        monkeypatch.setattr(RecordWriter, "write", _full_on_call(30, RecordWriter.write))
        return "tb"
    from matplotlib.figure import Figure

    monkeypatch.setattr(Figure, "savefig", _full_on_call(3, Figure.savefig))
    return "learning_curve.png"


@pytest.mark.parametrize("what", ["checkpoint", "metrics.csv", "tensorboard", "learning curve"])
def test_a_full_disk_stops_the_run_in_one_line_and_resume_goes_on(
    what: str, tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever file meets the full disk (on TensorBoard's thread too): one line naming it and what `--resume` goes
    on from, exit status 1; the latest checkpoint whole, no temporary file left; and once there is room the resume
    goes on, each batch logged once."""
    out = tmp_path / "run"
    named = _fill_the_disk(what, monkeypatch)
    rc, err = cli(capsys, "train", *QUICK, "--episodes", "160", "--out", str(out))
    lines = err.strip().splitlines()
    assert rc == 1 and len(lines) == 1 and "Traceback" not in err, err
    assert named in lines[0] and "No space left on device" in lines[0], lines[0]
    latest = json.loads((out / "checkpoints" / "latest.json").read_text())["checkpoint"]
    assert f"the run stopped; its latest checkpoint, {latest}, is whole: --resume" in lines[0]
    load_state(resolve(out))
    assert leftovers(out) == []
    monkeypatch.undo()
    rc, err = cli(capsys, "train", *QUICK, "--episodes", "160", "--out", str(out), "--resume")
    assert rc == 0, err
    rows = (out / "metrics.csv").read_text().splitlines()[1:]
    assert [row.split(",")[0] for row in rows] == [str(b) for b in range(1, 11)]


def test_a_finished_run_whose_last_curve_cannot_be_drawn_warns_in_one_line_and_succeeds(
    tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The curve is drawn from metrics.csv after the last checkpoint: a finished, saved run whose last drawing the
    disk refuses ends with status 0 and one warning naming the file and how to draw it (`--resume`, which does)."""
    from matplotlib.figure import Figure

    out = tmp_path / "run"
    monkeypatch.setattr(Figure, "savefig", _full_on_call(19, Figure.savefig))  # the 10th checkpoint's PNG: the last
    rc, err = cli(capsys, "train", *QUICK, "--episodes", "160", "--out", str(out))
    lines = err.strip().splitlines()
    assert rc == 0 and len(lines) == 1 and "Traceback" not in err, err
    assert "learning_curve.png" in lines[0] and "No space left on device" in lines[0], lines[0]
    assert lines[0].endswith(f"the run is finished and saved; `bitcomm train --resume --out {out}` draws it"), lines[0]
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"] == 160
    assert len((out / "metrics.csv").read_text().splitlines()) == 11 and leftovers(out) == []
    monkeypatch.undo()
    drawn = (out / "learning_curve.svg").stat().st_mtime_ns
    assert cli(capsys, "train", "--resume", "--out", str(out), "--quiet", "--eval-episodes", "0")[0] == 0
    assert (out / "learning_curve.svg").stat().st_mtime_ns > drawn


def test_torch_saves_full_disk_is_the_os_error_not_a_zip_writers_position(tmp_path: Path) -> None:
    """torch reports a write that failed as a RuntimeError about its zip writer; a checkpoint's state is written
    so that it is the OSError itself (here EFBIG: the file size limit a process may be given, `ulimit -f`)."""
    import resource

    from bitcomm.checkpoint import _torch_save

    limits = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails instead of killing
    resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, limits[1]))
    try:
        with pytest.raises(OSError) as caught:
            _torch_save({"w": torch.zeros(100_000)}, tmp_path / "state.pt")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, previous)
    assert caught.value.errno == errno.EFBIG


# ---------------------------------------------------------------------------------------------- NaN
def test_a_diverging_run_stops_and_keeps_its_last_good_checkpoint(
    tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    from bitcomm.learn.learner import Learner

    real_update, calls = Learner.update, []

    def update(self, *args, **kwargs):  # the third update blows a weight up
        stats = real_update(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 3:
            with torch.no_grad():
                next(self.policy.parameters()).view(-1)[0] = float("nan")
        return stats

    monkeypatch.setattr(Learner, "update", update)
    out = tmp_path / "run"
    line = refused(capsys, "train", *QUICK, "--episodes", "160", "--out", str(out), naming="diverged after 48 episodes")
    assert "NaN or inf" in line and "ckpt_000000032.safetensors" in line
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"] == 32
    assert [e for e, _ in checkpoints(out)] == [16, 32]
    weights, _ = load_weights(out)
    assert all(bool(torch.isfinite(t).all()) for sd in weights.values() for t in sd.values())
    monkeypatch.setattr(Learner, "update", real_update)  # the last good checkpoint resumes
    rc, err = cli(capsys, "train", *QUICK, "--episodes", "64", "--out", str(out), "--resume")
    assert rc == 0, err


def test_a_huge_learning_rate_ends_with_one_line(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    refused(capsys, "train", *QUICK, "--episodes", "64", "--lr", "1e30", "--out", str(out), naming="diverged")
    assert not (out / "checkpoints" / "latest.json").exists()


def test_save_checkpoint_writes_nothing_non_finite(tmp_path: Path) -> None:
    good = {"policy": {"w": torch.ones(3)}}
    save_checkpoint(tmp_path, {}, good, episodes=1, batches=1, state={})
    for bad_weights, state in (
        ({"policy": {"w": torch.tensor([1.0, float("inf")])}}, {}),
        (good, {"opt": {"state": {0: {"exp_avg": torch.tensor([float("nan")])}}}}),
    ):
        with pytest.raises(Diverged, match="the latest checkpoint stays ckpt_000000001"):
            save_checkpoint(tmp_path, {}, bad_weights, episodes=2, batches=2, state=state)
    assert [e for e, _ in checkpoints(tmp_path)] == [1]
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [
        "best.json",
        "ckpt_000000001.safetensors",
        "ckpt_000000001.state.pt",
        "latest.json",
    ]


def test_a_checkpoints_files_are_readable_as_the_umask_allows(tmp_path: Path) -> None:
    """Weights and state alike (safetensors' own writer made the weights owner-only): a shared run folder's
    checkpoints can be evaluated by whoever can read its config.json."""
    old = os.umask(0o022)
    try:
        weights = save_checkpoint(tmp_path, {}, {"policy": {"w": torch.ones(3)}}, episodes=1, batches=1, state={})
    finally:
        os.umask(old)
    state = weights.with_name("ckpt_000000001.state.pt")
    assert [stat.S_IMODE(f.stat().st_mode) for f in (weights, state)] == [0o644, 0o644]


# ---------------------------------------------------------------------------------------------- checksum
def _flip_last_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x40
    path.write_bytes(bytes(data))


def test_garbled_weights_or_state_are_refused(run: Path, capsys) -> None:
    weights_file = resolve(run)
    load_state(weights_file)  # intact: read without complaint
    state_file = weights_file.with_name(weights_file.name.replace(".safetensors", ".state.pt"))
    _flip_last_byte(state_file)
    refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", naming=state_file.name)
    _flip_last_byte(weights_file)  # a tensor's last byte: still a valid safetensors file
    line = refused(capsys, "eval", str(run), "--episodes", "10", naming=weights_file.name)
    assert "checksum mismatch" in line
    refused(capsys, "eval", str(weights_file), "--episodes", "10", naming="checksum mismatch")


@pytest.mark.parametrize("damaged", ["safetensors", "state.pt"])
def test_a_resume_of_a_damaged_latest_checkpoint_says_how_to_resume_from_the_one_before(
    damaged: str, run: Path, capsys
) -> None:
    """A fresh start would remove the run's earlier checkpoints: the line says how to go on from the newest of them,
    and doing what it says resumes. A resume that changes the config is not told about older checkpoints."""
    (older_episodes, older), (episodes, latest) = checkpoints(run)[-2:]
    _flip_last_byte(latest.with_name(latest.name.replace(".safetensors", f".{damaged}")))
    argv = ["train", *QUICK, "--out", str(run), "--resume", "--episodes", str(episodes + 16)]
    line = refused(capsys, *argv, naming="checksum mismatch")
    assert line.endswith(f"to resume from the older {older.name}, {pointed_at(older_episodes, older)}")
    (run / "checkpoints" / "latest.json").write_text(line.split(" as ", 1)[1])
    rc, err = cli(capsys, *argv)
    assert rc == 0, err
    assert checkpoints(run)[-1][0] == episodes + 16
    from bitcomm.learn.run import train

    with pytest.raises(ConfigError, match="invalid lr=0.5") as refusal:  # from Python, where the checkpoint says so
        train(tiny_config(lr=0.5, episodes=episodes + 32), run, resume=True, progress=False)
    assert "older" not in str(refusal.value)


class _Payload:
    """What a crafted resume state would run if it were unpickled: a file written beside the run."""

    def __init__(self, mark: Path) -> None:
        self.mark = mark

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (Path.touch, (self.mark,))


def test_a_resume_state_crafted_to_run_code_is_refused_in_one_line_unrun(run: Path, capsys) -> None:
    """A `.state.pt` holding a pickled call, its checksums rewritten to match (anyone can compute them), is refused
    by `torch.load(weights_only=True)`: one line saying why, without torch's advice to load it with
    `weights_only=False`, and the call never runs."""
    from safetensors import safe_open
    from safetensors.torch import save

    from bitcomm.checkpoint import content_sha256, file_sha256

    weights_file = resolve(run)
    state_file = weights_file.with_name(weights_file.name.replace(".safetensors", ".state.pt"))
    mark = run.parent / "ran"
    torch.save({**torch.load(state_file, weights_only=True), "payload": _Payload(mark)}, state_file)
    with safe_open(str(weights_file), framework="pt") as f:
        meta, tensors = dict(f.metadata()), {k: f.get_tensor(k).clone() for k in f.keys()}
    meta["state_sha256"] = file_sha256(state_file)
    meta["sha256"] = content_sha256(tensors, meta)
    weights_file.write_bytes(save(tensors, metadata=meta))
    line = refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", naming=state_file.name)
    assert "could run code" in line and "weights_only" not in line, line
    assert not mark.exists()


@pytest.mark.parametrize("path", [None, 5, ["runs/demo"]])
def test_a_path_that_is_neither_a_str_nor_a_path_is_one_line(path: object) -> None:
    """`Controller.load(None)` (a notebook's unset variable) was pathlib's TypeError, naming no argument."""
    from bitcomm import Controller, EnvController  # type: ignore[attr-defined]

    for load in (Controller.load, EnvController.load, load_weights):
        with pytest.raises(ConfigError, match=r"invalid path=.*: must be a run folder or a checkpoint file"):
            load(path)


@pytest.mark.parametrize("out", ["", None])
def test_a_run_folder_that_is_empty_or_no_path_is_one_line(out: object, tmp_path: Path, monkeypatch) -> None:
    """`train(cfg, "")` trained into the current folder (`--out ""` is refused), `train(cfg, None)` was pathlib's
    TypeError; neither writes anything."""
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.env_run import train_env
    from bitcomm.learn.run import train

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=f"invalid out={out!r}: must be the run's folder, a non-empty str or a Path"):
        train(tiny_config(), out, progress=False)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=f"invalid out={out!r}"):
        train_env(EnvTrainConfig(env="mpe2.simple_v3:parallel_env"), out, progress=False)  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []


def test_a_metrics_row_whose_episodes_is_no_count_is_one_line_on_resume(run: Path, capsys) -> None:
    """A hand edit or a damaged disk: it was a traceback from the TensorBoard writer's purge step, the resume begun."""
    metrics = run / "metrics.csv"
    *rows, last = metrics.read_text().splitlines()
    fields = last.split(",")
    fields[1] = "forty-eight"  # episodes
    metrics.write_text("\n".join([*rows, ",".join(fields)]) + "\n")
    before = metrics.read_text()
    line = refused(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64", naming="metrics.csv")
    assert "'forty-eight'" in line and "repair or remove it to resume" in line
    assert metrics.read_text() == before


def counted_loads(monkeypatch: pytest.MonkeyPatch, *sites: str) -> list[str]:
    """The paths `load_weights` is called with from now on, counted in `bitcomm.checkpoint` and at each module in
    `sites` that imported it by name (a site that no longer imports it is patched too, so a new import counts)."""
    from bitcomm import checkpoint

    loads: list[str] = []
    real = checkpoint.load_weights

    def counting(path):  # type: ignore[no-untyped-def]
        loads.append(str(path))
        return real(path)

    monkeypatch.setattr(checkpoint, "load_weights", counting)
    for site in sites:
        monkeypatch.setattr(f"{site}.load_weights", counting, raising=False)
    return loads


def test_eval_of_a_checkpoint_file_reads_its_tensors_once(run: Path, capsys, monkeypatch) -> None:
    """`bitcomm eval FILE` chooses between a grid and a wrapped-env run from the file's metadata alone; only the
    load that plays reads (and checks) the tensors."""
    file = resolve(run)
    assert read_config(file) == load_weights(file)[1]["config"]
    loads = counted_loads(monkeypatch, "bitcomm.learn.env_run")  # where the old choice read it
    rc, err = cli(capsys, "eval", str(file), "--episodes", "10", "--threads", "1")
    assert rc == 0, err
    assert loads == [str(file)]


def test_a_resume_reads_the_checkpoints_tensors_once(run: Path, capsys, monkeypatch) -> None:
    """`bitcomm train --resume` takes the run's config from the checkpoint's metadata; only the load that resumes
    reads (and checks) the tensors."""
    loads = counted_loads(monkeypatch, "bitcomm.learn.run_folder")  # where the old config and the resume read it
    rc, err = cli(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64")
    assert rc == 0, err
    assert len(loads) == 1


def test_tampered_metadata_is_refused(run: Path) -> None:
    from safetensors import safe_open
    from safetensors.torch import save_file

    file = resolve(run)
    with safe_open(str(file), framework="pt") as f:
        meta, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    save_file(tensors, str(file), metadata={**meta, "episodes": "1000000"})
    with pytest.raises(ConfigError, match="checksum mismatch"):
        load_weights(file)


# ---------------------------------------------------------------------------------------------- latest
@pytest.mark.parametrize(
    "pointer",
    ["../../outside.safetensors", "/etc/passwd", "../checkpoints/ckpt_000000016.safetensors", "ckpt_1.safetensors"],
)
def test_latest_cannot_leave_the_run_folder(run: Path, pointer: str, capsys) -> None:
    outside = run.parent / "outside.safetensors"
    shutil.copy(resolve(run), outside)
    (run / "checkpoints" / "latest.json").write_text(json.dumps({"checkpoint": pointer, "episodes": 16}))
    refused(capsys, "eval", str(run), "--episodes", "10", naming="latest.json")


def test_latest_cannot_follow_a_link_outside(run: Path, capsys) -> None:
    outside = run.parent / "elsewhere"
    outside.mkdir()
    file = resolve(run)
    shutil.move(file, outside / file.name)
    file.symlink_to(outside / file.name)
    refused(capsys, "eval", str(run), "--episodes", "10", naming="links outside the run folder")


# ---------------------------------------------------------------------------------------------- record
def test_each_start_and_resume_is_recorded_with_its_machine(run: Path, capsys) -> None:
    """A run resumed on another machine or commit says which part ran where; the first start's oracle is kept."""
    config = json.loads((run / "config.json").read_text())
    (start,) = config["starts"]
    assert start["episodes"] == 0 and start["machine"] == machine() and start["torch_threads"] >= 1
    assert start["git_commit"] == config["git_commit"] and start["versions"] == config["versions"]
    assert run_machines(run) == [machine_label(machine())]

    elsewhere = {**start, "machine": {"cpu": "Other CPU", "cores": 16}, "git_commit": "a" * 40}
    (run / "config.json").write_text(json.dumps({**config, "starts": [elsewhere]}))
    rc, err = cli(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64")
    assert rc == 0, err
    resumed = json.loads((run / "config.json").read_text())
    assert [s["episodes"] for s in resumed["starts"]] == [0, 48]
    assert resumed["starts"][0] == elsewhere and resumed["starts"][1]["machine"] == machine()
    assert resumed["oracle_mean_episode_length"] == config["oracle_mean_episode_length"]
    assert run_machines(run) == ["Other CPU, 16 cores", machine_label(machine())]

    # a run begun before starts were kept: its first start is what config.json said, machine unrecorded
    legacy = {k: v for k, v in resumed.items() if k != "starts"}
    (run / "config.json").write_text(json.dumps({**legacy, "git_commit": "b" * 40}))
    rc, err = cli(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "80")
    assert rc == 0, err
    starts = json.loads((run / "config.json").read_text())["starts"]
    assert [s["episodes"] for s in starts] == [0, 64] and starts[0]["git_commit"] == "b" * 40
    assert run_machines(run) == ["unrecorded", machine_label(machine())]


def test_each_start_records_its_budget_and_where_it_ran(run: Path) -> None:
    """config.json's config is the last start's: a run resumed to a larger budget from Python (whose command line
    does not show it) said nothing of the budget its first part decayed its learning rates over, nor where or how
    often that part saved; each start now records the options a resume may change as it had them."""
    import dataclasses

    from bitcomm.learn.run import train

    first = tiny_config()
    train(dataclasses.replace(first, episodes=64, checkpoint_seconds=5.0), run, resume=True, progress=False)
    starts = json.loads((run / "config.json").read_text())["starts"]
    assert [s["options"]["episodes"] for s in starts] == [first.episodes, 64]
    assert [s["options"]["checkpoint_seconds"] for s in starts] == [first.checkpoint_seconds, 5.0]
    assert starts[1]["options"]["backend"] == "local" and "lr" not in starts[1]["options"]


def tensorboard_scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    """Each TensorBoard tag of a run folder with its (step, value) pairs, as TensorBoard shows them."""
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    events = EventAccumulator(str(run / "tb"), size_guidance={SCALARS: 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def log_batches(out: Path, batches: range, resume_batches: int | None, value: float) -> None:
    """What a trainer logs: one row per batch of 16 episodes, into a Logger opened fresh or on a resume."""
    from bitcomm.learn.run_folder import Logger

    logger = Logger(out, resume_batches)
    for b in batches:
        logger.log({"batch": b, "episodes": 16 * b, "wall_s": 0.1 * b, "charts/episode_length": value + b})
    logger.close()


def test_tensorboard_and_metrics_csv_show_each_batch_once_after_a_resume(tmp_path: Path) -> None:
    """A `kill -9` leaves rows logged past the last checkpoint; the resume plays those batches again. TensorBoard
    shows each step once, in order, with the resumed run's values, as metrics.csv does (header once)."""
    log_batches(tmp_path, range(1, 5), None, 100.0)  # batches 3 and 4 logged, then killed before their checkpoint
    log_batches(tmp_path, range(3, 7), 2, 200.0)  # resumed from batch 2's checkpoint
    steps = [16 * b for b in range(1, 7)]
    assert tensorboard_scalars(tmp_path) == {
        "charts/episode_length": list(zip(steps, [101.0, 102.0, 203.0, 204.0, 205.0, 206.0], strict=True))
    }
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert lines[0].startswith("batch,") and [line.split(",")[0] for line in lines[1:]] == [str(b) for b in range(1, 7)]

    log_batches(tmp_path, range(1, 3), None, 300.0)  # a fresh run in the folder: the old run's events are gone too
    assert tensorboard_scalars(tmp_path) == {"charts/episode_length": [(16, 301.0), (32, 302.0)]}


def test_a_fresh_run_leaves_alone_a_tensorboard_folder_that_is_not_a_runs(tmp_path: Path, capsys) -> None:
    """A fresh run removes the event files of the run it replaces: in a folder that is not a run's, one line."""
    (tmp_path / "tb").mkdir()
    (tmp_path / "tb" / "events.out.tfevents.1.host.1.0").write_bytes(b"mine")
    refused(capsys, "train", *QUICK, "--episodes", "16", "--out", str(tmp_path), naming="tb")
    assert (tmp_path / "tb" / "events.out.tfevents.1.host.1.0").read_bytes() == b"mine"


def git(folder: Path, *args: str) -> str:
    return subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=folder, check=True, capture_output=True,
        text=True,
    ).stdout.strip()  # fmt: skip


def a_project_ignoring_its_venv(tmp_path: Path) -> Path:
    """A user's project under git, whose .venv (where bitcomm is installed) git ignores."""
    project = tmp_path / "project"
    project.mkdir()
    git(project, "init", "-q")
    (project / ".gitignore").write_text(".venv/\n")
    git(project, "add", ".")
    git(project, "commit", "-qm", "a project that installs bitcomm")
    return project


def package_in(folder: Path) -> Path:
    package = folder / "bitcomm"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    return package


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_the_commit_recorded_is_bitcomms_own_and_says_whether_its_source_was_changed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A checkout records its commit, and `git_dirty` once the package's source differs from it; an installed copy
    built without git records no commit, even inside another project's repository (a `.venv` in it), whose commit
    is not bitcomm's."""
    from bitcomm import provenance

    checkout = tmp_path / "checkout"
    package = package_in(checkout / "src")
    git(checkout, "init", "-q")
    git(checkout, "add", ".")
    git(checkout, "commit", "-qm", "bitcomm")
    monkeypatch.setattr(provenance, "PACKAGE", package)
    head = git(checkout, "rev-parse", "HEAD")
    assert provenance.git_state() == (head, False)
    (checkout / "notes.txt").write_text("outside the package\n")
    assert provenance.git_state() == (head, False)
    (package / "new_module.py").write_text("x = 1\n")
    assert provenance.git_state() == (head, True)
    record = provenance.record()
    assert tuple(record) == provenance.RECORDED and (record["git_commit"], record["git_dirty"]) == (head, True)

    project = a_project_ignoring_its_venv(tmp_path)
    monkeypatch.setattr(provenance, "PACKAGE", package_in(project / ".venv" / "site-packages"))
    assert provenance.git_state() == (None, None)
    monkeypatch.setattr(provenance, "PACKAGE", package_in(tmp_path / "site-packages"))
    assert provenance.git_state() == (None, None)


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_an_installed_copy_records_the_commit_it_was_built_from(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The build bakes the checkout's commit into the package it builds (setup.py); an installed copy, which no
    checkout tracks, records that one, even inside another project's repository, while a checkout asks git."""
    from bitcomm import commit, provenance

    checkout = tmp_path / "checkout"
    source = package_in(checkout / "src")
    git(checkout, "init", "-q")
    git(checkout, "add", ".")
    git(checkout, "commit", "-qm", "bitcomm")
    head = git(checkout, "rev-parse", "HEAD")
    project = a_project_ignoring_its_venv(tmp_path)
    installed = package_in(project / ".venv" / "site-packages")
    commit.bake(source, installed)
    monkeypatch.setattr(provenance, "PACKAGE", installed)
    assert provenance.git_state() == (head, False)
    record = provenance.record()
    assert tuple(record) == provenance.RECORDED and (record["git_commit"], record["git_dirty"]) == (head, False)

    (source / "new_module.py").write_text("x = 1\n")
    commit.bake(source, installed)  # built from a changed source
    assert provenance.git_state() == (head, True)
    (source / commit.BUILT).write_text(json.dumps({"git_commit": "a" * 40, "git_dirty": False}))
    monkeypatch.setattr(provenance, "PACKAGE", source)
    assert provenance.git_state() == (head, True)  # a checkout asks git, whatever file lies in it

    monkeypatch.setattr(provenance, "PACKAGE", installed)
    (installed / commit.BUILT).write_text("{not json")
    assert provenance.git_state() == (None, None)
    commit.bake(package_in(tmp_path / "sdist" / "src"), installed)  # a build from no checkout removes an old file
    assert not (installed / commit.BUILT).exists() and provenance.git_state() == (None, None)


def test_a_run_records_its_commit_whether_its_source_was_changed_and_its_libraries(run: Path) -> None:
    config = json.loads((run / "config.json").read_text())
    assert "git_commit" in config and config["git_dirty"] in (True, False, None)
    assert set(config["versions"]) >= {"python", "bitcomm", "torch", "numpy", "gymnasium", "pettingzoo"}


# ---------------------------------------------------------------------------------------------- leftovers
def test_resume_removes_what_a_kill_left(run: Path, capsys) -> None:
    folder = run / "checkpoints"
    junk = [
        folder / f".ckpt_000000064.safetensors.tmp{12345}",
        folder / ".latest.json.tmp99",
        run / ".config.json.tmp",
        folder / "ckpt_000000112.state.pt",  # killed between the state and the weights
        folder / "ckpt_000000128.safetensors",  # weights without their state
    ]
    for path in junk:
        path.write_bytes(b"partial")
    # a whole checkpoint newer than latest.json (killed before the pointer moved): never committed
    for suffix in ("safetensors", "state.pt"):
        shutil.copy(folder / f"ckpt_000000048.{suffix}", folder / f"ckpt_000000096.{suffix}")
    assert len(leftovers(run)) == 5
    rc, err = cli(capsys, "train", *QUICK, "--out", str(run), "--resume", "--episodes", "64")
    assert rc == 0, err
    assert leftovers(run) == [] and not any(p.exists() for p in junk)
    assert [e for e, _ in checkpoints(run)][-3:] == [32, 48, 64]


def test_clean_on_a_fresh_start_and_without_latest(tmp_path: Path) -> None:
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    for name in ("ckpt_000000016.safetensors", "ckpt_000000016.state.pt", ".latest.json.tmp3", "notes.txt"):
        (folder / name).write_text("x")
    assert sorted(clean(tmp_path)) == [".latest.json.tmp3", "ckpt_000000016.safetensors", "ckpt_000000016.state.pt"]
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]  # only bitcomm's own names are touched


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs kill -9")
def test_kill_9_then_resume_loses_at_most_one_interval(tmp_path: Path, capsys) -> None:
    out = tmp_path / "killed"
    args = ["train", *QUICK, "--episodes", "320"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", *args, "--out", str(out)],
        env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    latest = out / "checkpoints" / "latest.json"
    deadline = time.monotonic() + 90
    while proc.poll() is None and time.monotonic() < deadline:
        if latest.exists() and json.loads(latest.read_text())["episodes"] >= 48:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    played = json.loads(latest.read_text())["episodes"]
    assert 48 <= played < 320, "the run ended before it could be killed"
    with (out / "metrics.csv").open() as f:
        logged = sum(1 for _ in f) - 1
    assert logged * 16 - played <= 16  # at most the one batch after the checkpoint is lost
    rc, err = cli(capsys, *args, "--out", str(out), "--resume")
    assert rc == 0, err
    assert leftovers(out) == [] and json.loads(latest.read_text())["episodes"] == 320


def run_until_logged(args: list[str], out: Path, batches: int, **popen: Any) -> subprocess.Popen[str]:
    """`bitcomm ARGS --out OUT` in a process of its own (stderr piped), returned once it has logged `batches`
    batches, ended, or run 90 s: a run to stop with a signal part way."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", *args, "--out", str(out)],
        env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **popen,
    )  # fmt: skip
    metrics, deadline = out / "metrics.csv", time.monotonic() + 90
    while proc.poll() is None and time.monotonic() < deadline:
        if metrics.exists() and len(metrics.read_text().splitlines()) > batches:  # the header and the batches
            break
        time.sleep(0.01)
    return proc


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_saves_the_batch_it_stopped_after_and_resume_goes_on(
    tmp_path: Path, capsys, signum: signal.Signals
) -> None:
    """Ctrl-C, or the SIGTERM that `kill PID` and a scheduler's time limit send, loses no batch played."""
    out = tmp_path / "interrupted"
    args = ["train", *QUICK[:-1], "3600", "--episodes", "960"]  # no periodic checkpoint: only the stop saves
    # SIGINT's default handler, as in a terminal, even under CI
    proc = run_until_logged(args, out, 3, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    metrics = out / "metrics.csv"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err  # as a shell reports a process the signal ended
    played = json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"]
    logged = len(metrics.read_text().splitlines()) - 1
    assert 48 <= played < 960 and played == logged * 16, err  # every batch played is in the checkpoint
    assert f"stopped after {played} episodes on {signum.name}" in err and "Traceback" not in err
    rc, err = cli(capsys, *args, "--out", str(out), "--resume")
    assert rc == 0, err
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"] == 960


def test_a3c_stopped_as_timeout_does_saves_every_batch_leaks_nothing_and_resumes(tmp_path: Path, capsys) -> None:
    """`timeout` sends SIGTERM to the run, then to its process group (the workers, and the run again): the workers
    end after their batch, the main process saves and unlinks its semaphores (killed, it left the resource
    tracker's "leaked semaphore" warning)."""
    out = tmp_path / "a3c"
    args = ["train", *QUICK[:-1], "3600", "--mode", "a3c", "--workers", "2", "--episodes", "960"]
    proc = run_until_logged(args, out, 2, start_new_session=True)
    metrics = out / "metrics.csv"
    proc.send_signal(signal.SIGTERM)
    os.killpg(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)  # till the resource tracker, which would warn, closes stderr too
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "leaked" not in err and "Traceback" not in err, err
    played = json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"]
    assert played == (len(metrics.read_text().splitlines()) - 1) * 16 and f"stopped after {played} episodes" in err
    rc, err = cli(capsys, *args[:-1], str(played + 32), "--out", str(out), "--resume")
    assert rc == 0, err
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"] >= played + 32


def _spawned_children(pid: int) -> list[int]:
    """The pids of the `multiprocessing` spawned children of `pid` (its a3c workers; not the resource tracker)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if ppid == pid and b"spawn_main" in (entry / "cmdline").read_bytes():
                found.append(int(entry.name))
        except (ValueError, OSError, IndexError):
            continue
    return sorted(found)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the workers in /proc")
def test_an_a3c_worker_killed_outright_stops_the_run_saved_in_one_line(tmp_path: Path) -> None:
    """`kill -9` of one worker (or the OOM killer): the others stop after their batch and the run saves and ends
    in one line; before, they trained on to the budget unseen and the run ended in a traceback, nothing saved.
    A kill that lands while the worker holds the shared lock (its claim or optimizer step, a good part of a batch)
    leaves the weights unreadable: the run ends in one line saying so and where `--resume` goes on (a CI run met
    it; this test cannot choose the moment)."""
    out = tmp_path / "a3c"
    args = ["train", *QUICK[:-1], "3600", "--mode", "a3c", "--workers", "2", "--episodes", "96000"]
    proc = run_until_logged(args, out, 2, start_new_session=True)
    try:
        workers = _spawned_children(proc.pid)
        assert len(workers) == 2, workers
        os.kill(workers[1], signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and "Traceback" not in err, err
    assert _spawned_children(proc.pid) == []
    if "shared lock was not released" in lines[-1]:
        assert "a worker killed while it held it" in lines[-1] and RESUMES in lines[-1], err
        return
    assert "exit code -9" in lines[-1], err
    played = json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"]
    assert played == (len((out / "metrics.csv").read_text().splitlines()) - 1) * 16 and str(played) in lines[-1]


def test_an_a3c_run_from_a_script_without_the_main_guard_names_the_guard(tmp_path: Path) -> None:
    """multiprocessing's spawn runs the script again in each worker, where Python stops it; the run's line said only
    that worker 0 died (exit code 1). It now names the guard the script needs."""
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from bitcomm import ChannelConfig, EnvConfig, TaskConfig\n"
        "from bitcomm.learn.config import make_train_config\n"
        "from bitcomm.learn.run import train\n"
        "task = TaskConfig(EnvConfig(size=3, max_steps=8), ChannelConfig(bits=4))\n"
        "cfg = make_train_config('reinforced', task, mode='a3c', workers=1, num_envs=8, episodes=16)\n"
        f"train(cfg, {str(tmp_path / 'run')!r}, progress=False)\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=ENV, timeout=120)
    last = done.stderr.strip().splitlines()[-1]
    assert "a3c worker 0" in last and "died (exit code 1)" in last, done.stderr
    assert 'under `if __name__ == "__main__":`' in last


def test_an_a3c_runs_seconds_of_training_leave_out_its_workers_start(tmp_path: Path) -> None:
    """`wall_s` is seconds of training over all the run's starts: an a3c run counted its workers' spawn and imports
    (seconds on a busy machine) as training, at every start, so a resumed run showed more than the same run
    uninterrupted. A worker here starts `DELAY` s late (a `sitecustomize` that sleeps in spawned processes)."""
    delay = 3.0
    slow = tmp_path / "slow"
    slow.mkdir()
    (slow / "sitecustomize.py").write_text(
        f"import sys, time\nif '--multiprocessing-fork' in sys.argv:\n    time.sleep({delay})\n"
    )
    env = {**ENV, "PYTHONPATH": os.pathsep.join([str(slow), *sys.path])}
    out = tmp_path / "a3c"
    args = ["train", *QUICK, "--mode", "a3c", "--workers", "1", "--episodes", "32", "--out", str(out)]
    done = subprocess.run([sys.executable, "-m", "bitcomm.cli", *args], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    with (out / "metrics.csv").open(newline="") as f:
        first = next(csv.DictReader(f))
    assert float(first["wall_s"]) < delay, first  # one batch of 16 episodes on a 4x4 grid: a fraction of a second


def test_an_a3c_run_resumed_on_ray_is_one_line_that_can_be_followed(tmp_path: Path, capsys) -> None:
    """Ray trains in sync mode and a resume keeps the mode: the line was the config's own, which asked to change
    --mode (refused on a resume)."""
    args = ["train", *QUICK, "--mode", "a3c", "--workers", "1", "--episodes", "16", "--out", str(tmp_path / "a3c")]
    assert cli(capsys, *args)[0] == 0
    line = refused(capsys, *args, "--resume", "--backend", "ray", "--episodes", "32", naming="invalid backend='ray'")
    assert "mode=a3c" in line and "without --backend ray" in line


def test_a_stop_signal_repeated_at_once_is_one_request(monkeypatch: pytest.MonkeyPatch) -> None:
    """`timeout`'s second copy of its signal (`REPEAT_S`) must not stop the run unsaved; a later one does."""
    from bitcomm.learn import run_folder

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with run_folder.stop_after_batch() as stop_asked:
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGINT)
            assert stop_asked() == signal.SIGINT
            monkeypatch.setattr(run_folder, "REPEAT_S", 0.0)
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_stop_asked_while_the_last_checkpoint_is_saved_stops_the_run(tmp_path: Path) -> None:
    """Ctrl-C or SIGTERM while the last batch's checkpoint was saved (its plot takes a second) was dropped: the run
    went on to its final evaluation (`--eval-episodes`, minutes for a large grid) and exited 0. It stops, saved."""
    from types import SimpleNamespace

    from bitcomm.learn.run_folder import Progress, train_batches
    from bitcomm.stop_signals import Stopped

    cfg: Any = SimpleNamespace(episodes=32, num_envs=16, checkpoint_seconds=3600)
    prog = Progress()
    logger: Any = SimpleNamespace(log=lambda row: None, close=lambda: None)

    def play_and_learn() -> dict[str, Any]:
        prog.episodes += 16
        return {"episodes": prog.episodes}

    def save(rank: float | None) -> Path:
        if prog.episodes == cfg.episodes:  # the signal comes while the last checkpoint is written
            signal.raise_signal(signal.SIGINT)
        return tmp_path / f"ckpt{prog.episodes}"

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(Stopped) as stopped:
            train_batches(cfg, prog, logger, play_and_learn, save, lambda row: {}, progress=False)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert stopped.value.exit_code == 130
    assert stopped.value.episodes == 32 and stopped.value.checkpoint == tmp_path / "ckpt32"


def test_a_second_ctrl_c_while_the_stop_saves_waits_for_the_plot(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C again while the first one's checkpoint was saved stopped the run before its plot was drawn: the
    checkpoint held batches that learning_curve.png did not show (here, no curve at all). The second signal waits for
    the save, checkpoint and plot, and the run stops as the first asked, saved, exit 130."""
    from bitcomm.learn import run_folder
    from bitcomm.learn.run import train
    from bitcomm.stop_signals import Stopped

    monkeypatch.setattr(run_folder, "REPEAT_S", 0.0)  # every later signal is a second one
    log, plot = run_folder.Logger.log, run_folder.plot_learning_curve

    def log_then_ctrl_c(logger: Any, row: dict[str, float]) -> None:
        log(logger, row)
        if row["episodes"] == 32:  # the first Ctrl-C, while the second batch was played
            signal.raise_signal(signal.SIGINT)

    def ctrl_c_then_plot(*args: Any) -> Path:
        signal.raise_signal(signal.SIGINT)  # the second, once the checkpoint is written
        return plot(*args)

    monkeypatch.setattr(run_folder.Logger, "log", log_then_ctrl_c)
    monkeypatch.setattr(run_folder, "plot_learning_curve", ctrl_c_then_plot)
    out = tmp_path / "run"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt) as stopped:  # rather than pytest's own stop, where it is not `Stopped`
            train(tiny_config(episodes=64, checkpoint_seconds=3600.0), out, progress=False)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert isinstance(stopped.value, Stopped), "the second Ctrl-C cut the save short"
    assert stopped.value.exit_code == 130 and stopped.value.episodes == 32
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"] == 32
    assert (out / "learning_curve.png").is_file() and (out / "learning_curve.svg").is_file()


def test_a_study_worker_leaves_sigterm_to_its_parent() -> None:
    """`bitcomm compare` stops its runs with SIGTERM at once; only a process started as a program takes it over."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from bitcomm.learn.run_folder import _stoppable_signals

    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        assert signal.SIGTERM in _stoppable_signals()  # this process: pytest, started as a program
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            assert signal.SIGTERM not in pool.submit(_stoppable_signals).result(timeout=60)
    finally:
        signal.signal(signal.SIGTERM, previous)


# ---------------------------------------------------------------------------------------------- retention
def test_retention_keeps_the_last_n_and_the_best(tmp_path: Path) -> None:
    rolling = {16: 9.0, 32: 4.0, 48: 6.0, 64: 7.0, 80: 8.0}
    for e, length in rolling.items():
        w = {"policy": {"w": torch.full((2,), float(e))}}
        save_checkpoint(tmp_path, {}, w, episodes=e, batches=e // 16, state={}, rolling_length=length, keep=2)
    assert [e for e, _ in checkpoints(tmp_path)] == [32, 64, 80]
    assert rolling_length(checkpoints(tmp_path)[0][1]) == 4.0
    assert leftovers(tmp_path) == []


def test_retention_ranks_by_rank_where_one_is_recorded(tmp_path: Path) -> None:
    """A wrapped env's episodes may all have one length: there the best is the highest rolling return, recorded
    as rank = -return; a checkpoint without a rank (older files) is ranked by its rolling length."""
    ranks = {16: -1.0, 32: -5.0, 48: -2.0, 64: -3.0, 80: -4.0}
    for e, r in ranks.items():
        w = {"policy": {"w": torch.full((2,), float(e))}}
        save_checkpoint(tmp_path, {}, w, episodes=e, batches=e // 16, state={}, rolling_length=25.0, keep=2, rank=r)
    assert [e for e, _ in checkpoints(tmp_path)] == [32, 64, 80]
    assert rank(checkpoints(tmp_path)[0][1]) == -5.0
    old = tmp_path / "old"
    save_checkpoint(old, {}, {"policy": {"w": torch.zeros(2)}}, episodes=16, batches=1, state={}, rolling_length=7.0)
    assert rank(checkpoints(old)[0][1]) == 7.0


def test_a_wrapped_env_run_keeps_its_best_return(tmp_path: Path) -> None:
    import csv

    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.env_run import train_env

    cfg = EnvTrainConfig(env="mpe2.simple_speaker_listener_v4:parallel_env", episodes=96, num_envs=16,
                         hidden=(16,), checkpoint_seconds=0.0, keep_checkpoints=1)  # fmt: skip
    out = tmp_path / "run"
    train_env(cfg, out, progress=False)
    kept = checkpoints(out)
    with (out / "metrics.csv").open(newline="") as f:  # a checkpoint after every batch: the best is kept
        best = max(float(r["charts/team_return_rolling"]) for r in csv.DictReader(f))
    assert 1 <= len(kept) <= 2 and kept[-1][0] == 96
    assert min(rank(f) for _, f in kept) == pytest.approx(-best)


def test_a_run_keeps_keep_checkpoints(tmp_path: Path, capsys) -> None:
    import csv

    out = tmp_path / "run"
    rc, err = cli(capsys, "train", *QUICK, "--episodes", "80", "--keep-checkpoints", "2", "--out", str(out))
    assert rc == 0, err
    kept = checkpoints(out)
    assert 2 <= len(kept) <= 3 and [e for e, _ in kept][-2:] == [64, 80]
    with (out / "metrics.csv").open(newline="") as f:  # a checkpoint after every batch: the best is kept
        best = min(float(r["charts/episode_length_rolling"]) for r in csv.DictReader(f))
    assert min(rolling_length(f) for _, f in kept) == pytest.approx(best)


def test_best_json_names_the_kept_best_and_every_reader_takes_it(tmp_path: Path, capsys) -> None:
    rolling = {16: 9.0, 32: 4.0, 48: 6.0}
    for e, length in rolling.items():
        w = {"policy": {"w": torch.full((2,), float(e))}}
        save_checkpoint(tmp_path, {}, w, episodes=e, batches=e // 16, state={}, rolling_length=length, keep=1)
    best = json.loads((tmp_path / "checkpoints" / "best.json").read_text())
    assert best == {"checkpoint": "ckpt_000000032.safetensors", "state": "ckpt_000000032.state.pt", "episodes": 32,
                    "batches": 2}  # fmt: skip
    assert resolve(tmp_path / "checkpoints" / "best.json").name == "ckpt_000000032.safetensors"
    assert resolve(tmp_path / "checkpoints" / "latest.json").name == "ckpt_000000048.safetensors"
    (tmp_path / "checkpoints" / "best.json").write_text('{"checkpoint": "../../x.safetensors", "episodes": 1}')
    with pytest.raises(ConfigError, match="best.json"):
        resolve(tmp_path / "checkpoints" / "best.json")


def test_a_checkpoint_recorded_unranked_is_never_the_best(tmp_path: Path) -> None:
    """Between a run's held-out evaluations checkpoints are written with rank inf: the rolling mean, which
    ranks a checkpoint with no rank recorded, must not put one of them above an evaluated one."""
    for e, r in {16: 30.0, 32: float("inf"), 48: 20.0, 64: float("inf")}.items():
        w = {"policy": {"w": torch.full((2,), float(e))}}
        save_checkpoint(tmp_path, {}, w, episodes=e, batches=e // 16, state={}, rolling_length=1.0, keep=1, rank=r)
    assert [e for e, _ in checkpoints(tmp_path)] == [48, 64]
    assert json.loads((tmp_path / "checkpoints" / "best.json").read_text())["episodes"] == 48


def test_a_run_that_evaluates_keeps_the_checkpoint_that_played_the_held_out_set_best(tmp_path: Path, capsys) -> None:
    import csv

    from bitcomm.learn.held_out import HELD_OUT_COLUMN, held_out_seed
    from bitcomm.policies.evaluation import evaluate_checkpoint

    out = tmp_path / "run"
    argv = ["train", *QUICK, "--episodes", "160", "--held-out-every", "48", "--held-out-episodes", "64"]
    rc, err = cli(capsys, *argv, "--keep-checkpoints", "1", "--out", str(out))
    assert rc == 0, err
    with (out / "metrics.csv").open(newline="") as f:
        scores = {int(r["episodes"]): float(r[HELD_OUT_COLUMN]) for r in csv.DictReader(f) if r[HELD_OUT_COLUMN]}
    assert sorted(scores) == [48, 96, 144, 160]  # each batch that crosses a multiple of 48, and the end
    best = min(scores, key=lambda e: (scores[e], -e))
    assert json.loads((out / "checkpoints" / "best.json").read_text())["episodes"] == best
    assert [e for e, _ in checkpoints(out)] == sorted({best, 160})
    seed = json.loads((out / "config.json").read_text())["held_out_seed"]
    assert seed == held_out_seed(0) != 0
    again = evaluate_checkpoint(out / "checkpoints" / "best.json", 64, seed, greedy=True)
    assert again.mean_episode_length == pytest.approx(scores[best])  # the figure is greedy play of that set
    rc, err = cli(capsys, "eval", str(out / "checkpoints" / "best.json"), "--episodes", "8", "--json")
    assert rc == 0, err


@pytest.mark.parametrize("evaluates", [True, False])
def test_the_loop_ranks_each_checkpoint_by_the_evaluation_it_follows_and_the_others_not_at_all(
    tmp_path: Path, evaluates: bool
) -> None:
    """`train_batches` with a held-out evaluation every 32 episodes (batches of 16, a checkpoint after every batch):
    the checkpoints after an evaluation carry its figure, the ones between carry inf (never the best), and without
    an evaluation every checkpoint is ranked by the rolling mean (None)."""
    from types import SimpleNamespace

    import numpy as np

    from bitcomm.learn.held_out import HELD_OUT_COLUMN, HeldOut
    from bitcomm.learn.run_folder import Logger, Progress, train_batches

    cfg = SimpleNamespace(episodes=64, num_envs=16, checkpoint_seconds=0.0)
    held_out = HeldOut(32, iter([7.0, 3.0]).__next__) if evaluates else None
    prog, saved = Progress(), []

    def play_and_learn() -> dict:
        return prog.add_batch(np.full(16, 5), np.zeros(16), 160)

    def save(rank: float | None) -> Path:
        saved.append((prog.episodes, rank))
        return tmp_path

    train_batches(cfg, prog, Logger(tmp_path, None), play_and_learn, save, lambda row: {}, False, held_out)
    if evaluates:
        assert saved == [(16, math.inf), (32, 7.0), (48, math.inf), (64, 3.0)]
    else:
        assert saved == [(16, None), (32, None), (48, None), (64, None)]
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0]
    assert (HELD_OUT_COLUMN in header) == evaluates


def test_the_rolling_length_of_sampled_messages_leaves_out_the_greedy_senders_episodes() -> None:
    """From `greedy_senders_from` on, the rolling length mixes in episodes played with every sender's most likely
    message; the sampled column keeps the messages the run samples, and a checkpoint carries it."""
    import numpy as np

    from bitcomm.learn.run_folder import SAMPLED_ROLLING, Progress

    prog = Progress()
    row = prog.add_batch(np.array([10, 20, 30, 40]), np.zeros(4), 200, sent_greedy=np.array([True, True, False, False]))
    assert row["charts/episode_length_rolling"] == 25 and row[SAMPLED_ROLLING] == 35
    row = prog.add_batch(np.array([90, 50]), np.zeros(2), 280, sent_greedy=np.array([True, False]))
    assert row["charts/episode_length_rolling"] == 40 and row[SAMPLED_ROLLING] == (30 + 40 + 50) / 3
    assert SAMPLED_ROLLING not in prog.add_batch(np.array([5]), np.zeros(1), 10)  # an env run: no such episodes
    greedy_only = Progress().add_batch(np.array([5, 6]), np.zeros(2), 22, sent_greedy=np.array([True, True]))
    assert (
        SAMPLED_ROLLING not in greedy_only
    )  # nothing to average yet: no column rather than a None TensorBoard refuses
    resumed = Progress()
    resumed.restore({"episodes": 7, "batches": 3, **prog.state()})
    assert list(resumed.recent_sampled) == list(prog.recent_sampled) == [30, 40, 50]
    before = {k: v for k, v in prog.state().items() if k != "recent_sampled_lengths"}  # a checkpoint of session 36
    resumed = Progress()
    resumed.restore({"episodes": 7, "batches": 3, **before})
    assert list(resumed.recent_sampled) == list(prog.recent)


def test_a_run_with_greedy_senders_logs_and_plots_its_sampled_episodes_apart(capsys, tmp_path: Path) -> None:
    import csv

    from bitcomm.learn.run_folder import SAMPLED_ROLLING

    out = tmp_path / "run"
    flags = ["--episodes", "64", "--greedy-senders", "0.5", "--greedy-senders-from", "0.5", "--out", str(out)]
    rc, err = cli(capsys, "train", *QUICK, *flags)
    assert rc == 0, err
    with (out / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    first = [r for r in rows if int(r["episodes"]) <= 32]  # before halfway every message is sampled
    assert first and all(r[SAMPLED_ROLLING] == r["charts/episode_length_rolling"] for r in first)
    assert (out / "learning_curve.png").is_file()


def test_evaluations_leave_the_training_itself_unchanged(tmp_path: Path, capsys) -> None:
    """The held-out set is played on a copy with a generator of its own: weights after training are the same bit
    for bit as a run's that never evaluates."""
    weights, streams = [], []
    for flags in ([], ["--held-out-every", "32", "--held-out-episodes", "16", "--no-held-out-greedy"]):
        out = tmp_path / f"run{len(weights)}"
        rc, err = cli(capsys, "train", *QUICK, "--episodes", "96", *flags, "--out", str(out))
        assert rc == 0, err
        weights.append(load_weights(out)[0]["policy"])
        streams.append(load_state(resolve(out))["torch_rng"])  # the global generator, which training may draw from
    assert weights[0].keys() == weights[1].keys()
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert torch.equal(streams[0], streams[1])


def test_held_out_evaluation_is_refused_where_it_cannot_act(capsys, tmp_path: Path) -> None:
    refused(capsys, "train", *QUICK, "--held-out-every", "16", "--mode", "a3c", "--out", str(tmp_path / "x"),
            naming="held-out-every")  # fmt: skip
    refused(capsys, "train", *QUICK, "--held-out-every", "-1", "--out", str(tmp_path / "y"), naming="held-out-every")
    refused(capsys, "train", *QUICK, "--held-out-episodes", "0", "--out", str(tmp_path / "z"),
            naming="held-out-episodes")  # fmt: skip


def test_keep_checkpoints_is_checked(capsys, tmp_path: Path) -> None:
    refused(capsys, "train", *QUICK, "--keep-checkpoints", "0", "--out", str(tmp_path / "x"), naming="keep-checkpoints")


# ---------------------------------------------------------------------------------------------- compare
def test_compare_runs_hold_the_lock_and_refuse_a_tampered_latest(run: Path, tmp_path: Path) -> None:
    from bitcomm.studies.compare import CHOICES, Configuration, Run, execute, run_status

    study_run = Run(Configuration(CHOICES[0]), 0, tiny_config(), run)
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(run)], stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        with pytest.raises(ConfigError, match=f"pid {holder.pid}"):
            execute(study_run, 10, 0)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert not (run / "evaluation.json").exists()
    (run / "checkpoints" / "latest.json").write_text('{"checkpoint": 5}')
    with pytest.raises(ConfigError, match="latest.json"):
        run_status(study_run)
    (run / "config.json").write_text("[1]")
    with pytest.raises(ConfigError, match="config.json"):
        run_status(study_run)


def test_an_older_checkpoint_s_optimizer_resumes_fused_with_its_moments() -> None:
    """Checkpoints from before the fused Adam saved `fused: None` in each group; loading one must keep the
    moments and the learning rate it holds but step the way this code builds its optimizers."""
    cfg = make_train_config(task=TaskConfig(env=EnvConfig(size=4), channel=ChannelConfig(bits=4)))
    old = Learner(cfg)
    for opt in (old.opt_policy, old.opt_critic):
        for p in (p for g in opt.param_groups for p in g["params"]):
            p.grad = torch.ones_like(p)
        opt.step()
    saved = {"weights": {"policy": old.policy.state_dict(), "critic": old.critic.state_dict()}, **learner_state(old)}
    for name in ("opt_policy", "opt_critic"):
        for g in saved[name]["param_groups"]:
            g.update(fused=None, lr=1.25e-3)
    new = Learner(cfg)
    restore_learner(new, saved)
    for opt, before in ((new.opt_policy, old.opt_policy), (new.opt_critic, old.opt_critic)):
        assert all(g["fused"] is True and g["lr"] == 1.25e-3 for g in opt.param_groups)
        moments = [opt.state[p]["exp_avg"] for g in opt.param_groups for p in g["params"]]
        expected = [before.state[p]["exp_avg"] for g in before.param_groups for p in g["params"]]
        assert all(torch.equal(a, b) for a, b in zip(moments, expected, strict=True))
