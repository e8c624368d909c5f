"""`bitcomm render`: one frame per step (state after the step), GIF and PNG frames well formed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.policies.agent_policies import OracleAgent, RandomAgent
from bitcomm.policies.reference import OraclePolicy
from bitcomm.studies.render import record_episode, render_frames, save_gif, save_png_frames

TINY = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))


def episode_length(task: TaskConfig, seed: int) -> int:
    """The same episode played by the batched oracle in the plain env: an independent length."""
    env = VecGoalExchange(task, 1, seed=seed)
    oracle = OraclePolicy(task)
    while True:
        result, _ = env.step(*oracle(env.observe()))
        if result.finished.env_index.size:
            return int(result.finished.length[0])


def test_record_matches_the_simulator_and_ends_on_the_goals() -> None:
    for seed in range(5):
        record = record_episode(OracleAgent(TINY), TINY, seed=seed)
        assert record.length == episode_length(TINY, seed)
        assert record.success
        np.testing.assert_array_equal(record.positions[-1], record.goals)
        assert record.positions.shape == (record.length + 1, 2)
        # the oracle sends the goal it sees: agent i sees agent (i + 1) % 2's goal
        np.testing.assert_array_equal(record.sent[0, 0], [int(c) for c in f"{record.goals[1]:04b}"])


def test_truncated_episode_has_max_steps_frames(tmp_path: Path) -> None:
    task = TaskConfig(EnvConfig(size=6, max_steps=5), ChannelConfig(bits=6))
    record = record_episode(RandomAgent(task, seed=1), task, seed=3)
    assert record.length == 5 and not record.success
    frames = render_frames(record)
    assert len(frames) == 5
    gif = save_gif(frames, tmp_path / "t.gif")
    with Image.open(gif) as im:
        assert im.n_frames == 5


def test_a_gif_stopped_as_it_is_written_leaves_the_one_before(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`render` stopped (Ctrl-C, a full disk) as it wrote the GIF left half of one in place of the one before."""
    task = TaskConfig(EnvConfig(size=6, max_steps=5), ChannelConfig(bits=6))
    frames = render_frames(record_episode(RandomAgent(task, seed=1), task, seed=3))
    gif = save_gif(frames, tmp_path / "t.gif")
    before = gif.read_bytes()
    save = Image.Image.save

    def half_then_stop(image: Image.Image, fp: Any, *args: Any, **kwargs: Any) -> None:
        save(image, fp, *args, **kwargs)
        Path(fp).write_bytes(Path(fp).read_bytes()[:100])
        raise KeyboardInterrupt

    monkeypatch.setattr(Image.Image, "save", half_then_stop)
    with pytest.raises(KeyboardInterrupt):
        save_gif(frames[:2], gif)
    assert gif.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["t.gif"]


def test_png_frames_stopped_as_one_is_written_leave_no_half_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`render --frames-dir` stopped (SIGTERM, Ctrl-C) as it wrote a frame left that frame half written."""
    task = TaskConfig(EnvConfig(size=6, max_steps=5), ChannelConfig(bits=6))
    frames = render_frames(record_episode(RandomAgent(task, seed=1), task, seed=3))
    save = Image.Image.save
    written: list[Any] = []

    def half_the_second_then_stop(image: Image.Image, fp: Any, *args: Any, **kwargs: Any) -> None:
        save(image, fp, *args, **kwargs)
        written.append(fp)
        if len(written) == 2:
            Path(fp).write_bytes(Path(fp).read_bytes()[:100])
            raise KeyboardInterrupt

    monkeypatch.setattr(Image.Image, "save", half_the_second_then_stop)
    with pytest.raises(KeyboardInterrupt):
        save_png_frames(frames, tmp_path / "frames")
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "frames").iterdir()] == ["frame_001.png"]
    Image.open(tmp_path / "frames" / "frame_001.png").load()


def test_cli_writes_gif_and_png_frames(tmp_path: Path) -> None:
    gif, frames = tmp_path / "ep.gif", tmp_path / "frames"
    cmd = [sys.executable, "-m", "bitcomm.cli", "render", "--policy", "oracle", "--size", "4", "--bits", "4",
           "--seed", "2", "--out", str(gif), "--frames-dir", str(frames)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    length = episode_length(TINY, 2)
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames == length
        width, height = im.size
        assert width >= 4 * 14 and height > width // 2
    pngs = sorted(frames.glob("frame_*.png"))
    assert len(pngs) == length
    with Image.open(pngs[0]) as first:
        assert first.size == (width, height)


def test_run_without_controller_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from bitcomm.cli import main
    from bitcomm.policies.source import LEARNED_UNAVAILABLE

    try:
        import bitcomm

        has_controller = hasattr(bitcomm, "Controller")
    except ImportError:
        has_controller = False
    if has_controller:
        return  # the learned path is tested where Controller lives
    assert main(["render", str(tmp_path / "no-such-run"), "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and LEARNED_UNAVAILABLE in err


def test_out_in_a_file_names_that_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`--out afile/x.gif`, `afile` a file: the line said the .gif path "is a file, not a folder"."""
    from bitcomm.cli import main

    (tmp_path / "afile").write_text("a file\n")
    assert main(["render", "--policy", "oracle", "--out", str(tmp_path / "afile" / "x.gif")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].endswith(f": {str(tmp_path / 'afile')!r} is a file, not a folder, so nothing can be written in it")


def test_threads_flag_sets_torchs_threads_for_a_trained_run(tmp_path: Path, threads, capsys) -> None:
    """`--threads N` (as on eval): a trained RUN's episode is played on N torch threads; the oracle never loads
    torch, so it is not set there; 0 is one error line."""
    import torch

    import bitcomm.studies.render as study
    from bitcomm.checkpoint import save_checkpoint
    from bitcomm.cli import main
    from bitcomm.learn.config import make_train_config
    from bitcomm.policies.networks import PolicyNet

    cfg = make_train_config("reinforced", TaskConfig(EnvConfig(size=4, max_steps=6), ChannelConfig(bits=4)))
    torch.manual_seed(0)
    run = tmp_path / "run"  # one checkpoint of an untrained policy, written by the trainer's own writer
    save_checkpoint(run, cfg.to_dict(), {"policy": PolicyNet(cfg.task, cfg.model).state_dict()}, 16, 1, state={})
    threads.watch(study, "record_episode")
    want = threads.want
    assert main(["render", str(run), "--threads", str(want), "--out", str(tmp_path / "run.gif")]) == 0
    assert threads.calls == threads.seen == [want]
    oracle = ["render", "--policy", "oracle", "--size", "4", "--bits", "4", "--threads", str(want)]
    assert main([*oracle, "--out", str(tmp_path / "oracle.gif")]) == 0
    assert threads.calls == [want] and len(threads.seen) == 2
    assert threads.zero_is_one_line("render", capsys)
