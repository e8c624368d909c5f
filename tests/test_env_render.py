"""`bitcomm render RUN` for a run trained on a wrapped PettingZoo env (issue 18): one frame per step, the env's
own picture and each agent's bits; the episode `bitcomm eval RUN --seed S --episodes 1` plays; one error line
for an env that cannot draw itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo import ParallelEnv
from PIL import Image

from bitcomm.cli import main
from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
from bitcomm.learn.env_eval import evaluate_env
from bitcomm.learn.env_run import train_env
from bitcomm.studies.env_render import EnvEpisodeRecord, record_env_episode, step_lines

SPEC = f"{__name__}:DrawnSignalEnv"
pytestmark = pytest.mark.usefixtures("trust_test_envs")  # every test reads back a run on this module's env


class DrawnSignalEnv(ParallelEnv):
    """A speaker sees a random bit; from step 1 on, the listener (2 actions) earns 1 when its action equals it.
    `render()` draws the bit (left half) and the step (right half) into a 12x16 picture; with `draws` false
    it returns None. Episodes last `steps` steps."""

    metadata = {"name": "drawn_signal_v0", "render_modes": ["rgb_array"]}

    def __init__(self, steps: int = 4, render_mode: str | None = None, draws: bool = True) -> None:
        self.possible_agents = ["speaker", "listener"]
        self.agents: list[str] = []
        self.steps, self.render_mode, self.draws = steps, render_mode, draws
        self._obs = {"speaker": spaces.Box(0, 1, (1,), np.float32), "listener": spaces.Box(0, 1, (1,), np.float32)}
        self._act = {"speaker": spaces.Discrete(1), "listener": spaces.Discrete(2)}

    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self._act[agent]

    def _observe(self) -> dict[str, np.ndarray]:
        return {"speaker": np.array([self.bit], np.float32), "listener": np.array([self.t / self.steps], np.float32)}

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.bit, self.t = int(np.random.default_rng(seed).integers(2)), 0
        self.agents = list(self.possible_agents)
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        r = float(self.t >= 1 and int(actions["listener"]) == self.bit)
        self.t += 1
        acting, done = list(self.agents), self.t >= self.steps
        self.agents = [] if done else acting
        obs = self._observe()
        return {a: obs[a] for a in acting}, {a: r for a in acting}, {a: False for a in acting}, \
            {a: done for a in acting}, {a: {} for a in acting}  # fmt: skip

    def render(self) -> np.ndarray | None:
        if not self.draws:
            return None
        image = np.zeros((12, 16, 3), np.uint8)
        image[:, :8, 0] = 255 * self.bit
        image[:, 8:, 1] = 40 * self.t
        return image


def without_render_mode(steps: int = 4) -> DrawnSignalEnv:
    """A factory that does not take `render_mode`."""
    return DrawnSignalEnv(steps)


def trained(out: Path, env: str = SPEC, **env_kwargs: Any) -> Path:
    cfg = EnvTrainConfig(
        env=env, env_kwargs=env_kwargs, channel=EnvChannelConfig(bits=2, topology=[["speaker", "listener"]]),
        episodes=16, num_envs=8, hidden=(16,), checkpoint_seconds=1e9,
    )  # fmt: skip
    train_env(cfg, out, progress=False)
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return trained(tmp_path_factory.mktemp("drawn") / "run")


def test_gif_has_one_frame_per_step_of_the_episode_eval_plays_first(run: Path, tmp_path: Path) -> None:
    gif, frames = tmp_path / "ep.gif", tmp_path / "frames"
    assert main(["render", str(run), "--seed", "3", "--out", str(gif), "--frames-dir", str(frames)]) == 0
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames == 4
    assert len(sorted(frames.glob("frame_*.png"))) == 4
    for seed in range(5):
        record = record_env_episode(run, seed)
        first = evaluate_env(run, 1, seed)  # the same episode: same length and return
        assert record.length == first.mean_episode_length == 4
        assert record.team_rewards.sum() == pytest.approx(first.mean_team_return)
    # the picture is the env's after each step: its right half shows the step
    assert [int(im[0, -1, 1]) for im in record.images] == [40, 80, 120, 160]


def hand_record() -> EnvEpisodeRecord:
    """Speaker sends 10 at step 0 (arrives), 01 at step 1 (dropped); the listener hears it with delay 1."""
    sent = np.array([[[1, 0], [0, 0]], [[0, 1], [1, 1]], [[1, 1], [0, 0]]], np.uint8)
    received = np.zeros((3, 2, 1, 2), np.uint8)
    received[1, 1, 0] = [1, 0]
    dropped = np.array([[False, False], [True, False], [False, False]])
    return EnvEpisodeRecord(
        SPEC, ("speaker", "listener"), np.array([[-1], [0]]), 1, np.array([True, False]), (1, 2), True,
        np.array([[0, 1], [0, 0], [0, 1]]), sent, received, dropped, np.ones((3, 2), bool),
        np.array([0.0, 1.0, 1.0]), [np.zeros((2, 2, 3), np.uint8)] * 3,
    )  # fmt: skip


def test_text_shows_the_bits_sent_and_received_and_the_drops() -> None:
    record = hand_record()
    lines = [step_lines(record, t) for t in range(3)]
    assert lines[2][0] == "step 3/3  team reward +1.000  return so far +2.000"
    assert lines[0][1] == "speaker  action fixed  |  sent 10 (=2)  |  received -"
    assert lines[0][2] == "listener  action 1  |  sent 00 (=0) (heard by no one)  |  received 00<-speaker (none yet)"
    assert lines[1][1] == "speaker  action fixed  |  sent 01 (=1) DROPPED  |  received -"
    assert lines[1][2].endswith("received 10<-speaker")
    assert lines[2][2].endswith("received 00<-speaker (dropped)")
    box = record._replace(discrete=False, fixed=np.array([False, False]), actions=np.full((3, 2, 2), 0.5))
    assert step_lines(box, 0)[1].startswith("speaker  action [+0.50]  |")  # its own action size: 1
    spaces_of = (spaces.Discrete(1), spaces.MultiDiscrete([2, 3], start=[1, 1]))  # index 1: combination (1, 2)
    assert step_lines(record._replace(action_spaces=spaces_of), 0)[2].startswith("listener  action [1 2]  |")
    gone = record._replace(alive=np.array([[True, True], [True, True], [False, True]]))
    assert step_lines(gone, 2)[1] == "speaker  gone"
    late = record._replace(alive=np.array([[False, True], [True, True], [True, True]]))  # the speaker joins at step 1
    assert step_lines(late, 0)[1] == "speaker  not here yet"
    assert step_lines(late, 1)[2].endswith("<-speaker (not here yet)")  # what it sent at step 0: nothing


def test_recorded_bits_are_what_the_channel_carried(run: Path) -> None:
    record = record_env_episode(run, seed=1)
    # delay 1, no noise: what the listener reads at t + 1 is what the speaker sent at t
    np.testing.assert_array_equal(record.received[1:, 1, 0], record.sent[:-1, 0])
    cut = record_env_episode(run, seed=1, drop_prob=1.0)
    assert cut.dropped.all() and not cut.received.any()
    assert all("DROPPED" in step_lines(cut, t)[1] for t in range(cut.length))


@pytest.mark.parametrize(
    ("env", "kwargs", "says"),
    [(SPEC, {"draws": False}, "render() returned None"), (f"{__name__}:without_render_mode", {}, "TypeError")],
)
def test_env_that_cannot_draw_is_one_error_line(
    env: str, kwargs: dict[str, Any], says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = trained(tmp_path / "run", env, **kwargs)
    capsys.readouterr()
    assert main(["render", str(run), "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and env in err and "render_mode='rgb_array'" in err and says in err
    assert not (tmp_path / "x.gif").exists()


@pytest.mark.parametrize(("flags", "says"), [(["--size", "5"], "--drop-prob"), (["--policy", "oracle"], "not both")])
def test_grid_flags_are_one_error_line(
    flags: list[str], says: str, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["render", str(run), "--out", str(tmp_path / "x.gif"), *flags]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err


@pytest.mark.parametrize(
    "command",
    [["analyze", "--out", "T/a"], ["deploy"], ["export", "--onnx", "T/x.onnx"], ["variance", "--out", "T/a"]],
    ids=lambda c: c[0],
)
def test_commands_for_grid_runs_refuse_an_env_run_in_one_line(
    command: list[str], run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Where it was a KeyError of the grid's config ('task'), the line names the env and the commands that read it."""
    name, *flags = command
    assert main([name, str(run), *(f.replace("T", str(tmp_path)) for f in flags)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"trained on a wrapped env ({SPEC})" in err and "bitcomm eval" in err
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # nothing written


def test_mpe2_speaker_listener(tmp_path: Path) -> None:
    pytest.importorskip("mpe2")
    run, gif = tmp_path / "sl", tmp_path / "sl.gif"
    spec = "mpe2.simple_speaker_listener_v4:parallel_env"
    assert main(["train", "--env", spec, "--episodes", "64", "--num-envs", "32", "--bits", "2", "--out", str(run),
                 "--quiet", "--eval-episodes", "0"]) == 0  # fmt: skip
    assert main(["render", str(run), "--out", str(gif)]) == 0
    with Image.open(gif) as im:
        assert im.n_frames == 25 and im.size[0] >= 700


def test_a_float_picture_in_0_1_is_drawn_in_its_colours_not_black() -> None:
    """An env whose `render()` gives floats in [0, 1] (matplotlib's convention) was cast to uint8 as it was: every
    pixel 0 or 1, a black frame. It is scaled to [0, 255]; a float picture already in [0, 255] is only rounded."""
    from bitcomm.studies.env_render import picture

    class Painted:
        def __init__(self, image: np.ndarray) -> None:
            self.image = image

        def render(self) -> np.ndarray:
            return self.image

    grey = np.full((2, 3, 3), 0.5)
    assert picture(Painted(grey), "x").tolist() == np.full((2, 3, 3), 128, np.uint8).tolist()
    assert picture(Painted(grey * 255 + 0.4), "x").max() == 128
    assert picture(Painted(np.full((2, 3, 3), 200, np.uint8)), "x").max() == 200
