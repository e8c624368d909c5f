"""`bitcomm train` / `bitcomm eval` / `Controller` on a tiny task: the run folder, a kill and a resume,
bit-for-bit reproducibility, Controller against the evaluator, and one-line errors for bad input."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from test_run_folder import tensorboard_scalars

TINY = ["--size", "4", "--bits", "4", "--max-steps", "16", "--num-envs", "16"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
BUDGET = 160  # 10 batches of 16 episodes


def bitcomm(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    out = subprocess.run(
        [sys.executable, "-m", "bitcomm.cli", *args], capture_output=True, text=True, env=ENV, timeout=120
    )
    if check:
        assert out.returncode == 0, out.stderr
    return out


def tiny_config(**kw):
    from bitcomm.learn.config import make_train_config

    task = TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=4))
    return make_train_config(
        "reinforced", task, **{"num_envs": 16, "episodes": BUDGET, "checkpoint_seconds": 0.0, **kw}
    )


def rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def learning_columns(run: Path) -> list[dict[str, str]]:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows(run)]


def weights(run: Path) -> dict[str, torch.Tensor]:
    from bitcomm.checkpoint import load_weights

    w, _ = load_weights(run)
    return {f"{p}.{k}": v for p, sd in w.items() for k, v in sd.items()}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("train") / "run"
    res = bitcomm("train", *TINY, "--episodes", "48", "--quiet", "--eval-episodes", "50", "--out", str(out))
    assert str(out) in res.stdout and "mean episode length" in res.stdout
    return out


def test_train_writes_run_folder(run_dir: Path) -> None:
    config = json.loads((run_dir / "config.json").read_text())
    assert config["seed"] == 0 and "git_commit" in config and "command" in config
    assert set(config["versions"]) >= {"python", "torch", "numpy", "bitcomm"}
    assert config["task"]["env"]["size"] == 4
    r = rows(run_dir)
    assert [int(x["episodes"]) for x in r] == [16, 32, 48]
    assert {"agent_steps", "charts/episode_length", "charts/episode_length_rolling", "losses/policy"} <= set(r[0])
    assert any((run_dir / "tb").iterdir())
    assert (run_dir / "learning_curve.png").stat().st_size > 0
    assert (run_dir / "learning_curve.svg").read_text().startswith("<?xml")
    latest = json.loads((run_dir / "checkpoints" / "latest.json").read_text())
    assert latest["episodes"] == 48 and (run_dir / "checkpoints" / latest["checkpoint"]).is_file()
    assert (run_dir / "checkpoints" / latest["state"]).is_file()


def test_sync_runs_are_reproducible(tmp_path: Path) -> None:
    from bitcomm.learn.run import train

    torch.set_num_threads(1)
    for name in ("a", "b"):
        train(tiny_config(), tmp_path / name, progress=False)
    assert learning_columns(tmp_path / "a") == learning_columns(tmp_path / "b")
    wa, wb = weights(tmp_path / "a"), weights(tmp_path / "b")
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)

    # a run killed after its first checkpoint and resumed ends exactly where the uninterrupted one did
    killed = tmp_path / "killed"
    args = ["train", *TINY, "--episodes", str(BUDGET), "--checkpoint-seconds", "0", "--quiet", "--eval-episodes", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", *args, "--out", str(killed)],
        env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    latest = killed / "checkpoints" / "latest.json"
    deadline = time.monotonic() + 60
    while not latest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert json.loads(latest.read_text())["episodes"] < BUDGET, "the run ended before it could be killed"
    bitcomm(*args, "--out", str(killed), "--resume")
    assert learning_columns(killed) == learning_columns(tmp_path / "a")
    assert tensorboard_scalars(killed) == tensorboard_scalars(tmp_path / "a")  # each step once, as a run in one go
    wk = weights(killed)
    assert all(torch.equal(wa[k], wk[k]) for k in wa)


def train_whole_and_in_pieces(tmp_path: Path, **options: Any) -> None:
    """The tiny run with `options` trained whole into `tmp_path / "whole"`, and into `tmp_path / "pieces"` in two
    halves (the second resumed from the first's checkpoint), on one schedule over the whole budget."""
    from bitcomm.learn.config import TrainConfig
    from bitcomm.learn.run import train
    from bitcomm.learn.run_folder import resume_config

    options["anneal_episodes"] = BUDGET
    train(tiny_config(**options), tmp_path / "whole", progress=False)
    train(tiny_config(**options, episodes=BUDGET // 2), tmp_path / "pieces", progress=False)
    pieces = resume_config(tmp_path / "pieces", TrainConfig.from_dict, BUDGET)
    train(pieces, tmp_path / "pieces", resume=True, progress=False)


def test_greedy_senders_wait_for_the_protocol_and_a_checkpoint_keeps_where_it_formed(tmp_path: Path) -> None:
    """`senders_wait_below`: a run whose rolling length never reaches the level plays no greedy senders' episode; one
    that reaches it before the senders' `_from` is the run without the wait, bit for bit (the paper's task, where the
    protocol forms in the budget's first quarter); and one that reaches it after, trained in two pieces, ends where
    the unbroken one did."""
    from bitcomm.learn.run import train

    torch.set_num_threads(1)
    sampled, mixed = "charts/episode_length_sampled_rolling", "charts/episode_length_rolling"
    train(tiny_config(senders_wait_below=0.01), tmp_path / "never", progress=False)
    assert all(r[sampled] == r[mixed] for r in rows(tmp_path / "never"))
    # 100x the oracle's length: reached at the second update (the first sees no rolling length), progress 0.1
    train(tiny_config(senders_wait_below=100.0), tmp_path / "early", progress=False)
    train(tiny_config(senders_wait_below=0.0), tmp_path / "plain", progress=False)
    early = [
        {k: v for k, v in r.items() if k != "schedule/protocol_formed"} for r in learning_columns(tmp_path / "early")
    ]
    assert early == learning_columns(tmp_path / "plain")
    assert rows(tmp_path / "plain")[-1][sampled] != rows(tmp_path / "plain")[-1][mixed]  # the senders did play

    train_whole_and_in_pieces(tmp_path, senders_wait_below=100.0, greedy_senders_from=0.0)
    assert [r[sampled] == r[mixed] for r in rows(tmp_path / "whole")][:3] == [True, True, False]
    assert learning_columns(tmp_path / "pieces") == learning_columns(tmp_path / "whole")


def test_a_move_decay_that_waited_resumes_where_it_started(tmp_path: Path) -> None:
    """The progress where a `move_decay_below` decay started is in the checkpoint: a run trained in two pieces
    ends where the unbroken one did, move scale and weights alike."""
    torch.set_num_threads(1)
    train_whole_and_in_pieces(tmp_path, move_decay_below=100.0)  # starts on the second batch
    scales = [float(r["schedule/move_scale"]) for r in rows(tmp_path / "whole")]
    assert scales[0] == 1.0 and scales[1] == 1.0 and scales[-1] == pytest.approx(1 / 9)  # from 1/10 to 9/10
    assert learning_columns(tmp_path / "pieces") == learning_columns(tmp_path / "whole")
    wa, wb = weights(tmp_path / "whole"), weights(tmp_path / "pieces")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_eval_json_and_controller(run_dir: Path) -> None:
    from bitcomm import Controller
    from bitcomm.policies.agent import NetworkPolicy
    from bitcomm.policies.evaluation import evaluate

    res = bitcomm("eval", str(run_dir), "--episodes", "100", "--seed", "3", "--greedy", "--json")
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert set(got) == {"episodes", "mean_episode_length", "ci95", "mean_team_return", "success_rate"}

    c = Controller.load(run_dir)
    assert c.task.env.size == 4 and c.config["estimator"] == "improved"
    planes = np.zeros((5, 2, 4, 4), np.uint8)
    planes[:, 0, 0, 0] = planes[:, 1, 3, 3] = 1
    received = np.zeros((5, c.task.slots, 4), np.uint8)
    move, bits = c.act(planes[0], received[0])
    assert np.shape(move) == () and bits.shape == (4,) and bits.dtype == np.uint8
    moves, bits = c.act(planes, received, greedy=True)
    assert moves.shape == (5,) and bits.shape == (5, 4)
    assert np.array_equal(c.act(planes[:1], received[:1], greedy=True)[0], moves[:1])
    # planes and bits hold 0 or 1: a robot's 0.5 or NaN is one error line, not a silent cast to uint8
    with pytest.raises(ConfigError, match=r"^invalid planes value 0\.5: every entry must be 0 or 1$"):
        c.act(planes * 0.5, received)
    with pytest.raises(ConfigError, match=r"^invalid received_bits value 2: every entry must be 0 or 1$"):
        c.act(planes, received + 2)

    # the trainer's own acting path (NetworkPolicy) and `bitcomm eval --greedy` play the same episodes alike
    ours = evaluate(NetworkPolicy(c.policy, greedy=True), c.task, 100, seed=3)
    assert ours.mean_episode_length == got["mean_episode_length"]
    assert ours.success_rate == got["success_rate"]

    # Controller.act itself, fed the simulator's observations one batch at a time, plays the same
    def direct(obs: Any) -> tuple[np.ndarray, np.ndarray]:
        B, n = obs.planes.shape[:2]
        moves, bits = c.act(obs.planes.reshape(B * n, 2, 4, 4), obs.received.reshape(B * n, -1, 4), greedy=True)
        return moves.reshape(B, n), bits.reshape(B, n, 4)

    assert evaluate(direct, c.task, 100, seed=3).mean_episode_length == got["mean_episode_length"]


def test_controller_sampling_matches_eval(run_dir: Path) -> None:
    from bitcomm import Controller
    from bitcomm.policies.agent_policies import BatchedPolicy, ControllerAgent
    from bitcomm.policies.evaluation import evaluate

    res = bitcomm("eval", str(run_dir), "--episodes", "100", "--seed", "5", "--json")
    got = json.loads(res.stdout.strip().splitlines()[-1])
    c = Controller.load(run_dir, seed=5)
    ours = evaluate(BatchedPolicy(ControllerAgent(c)), c.task, 100, seed=5)
    assert ours.to_dict() == got


def test_evaluate_takes_a_controller_as_bitcomm_exports_both(run_dir: Path) -> None:
    """`bitcomm.evaluate(bitcomm.Controller.load(RUN))` is what a newcomer writes: it plays the run's own task as
    `bitcomm eval RUN` does (it failed with "'Controller' object is not callable"); anything else is named."""
    import bitcomm as api

    res = bitcomm("eval", str(run_dir), "--episodes", "100", "--seed", "5", "--json")
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert api.evaluate(api.Controller.load(run_dir, seed=5), episodes=100, seed=5).to_dict() == got
    with pytest.raises(ConfigError, match="invalid policy=3: must be a bitcomm.Controller or a callable"):
        api.evaluate(3, api.TaskConfig())  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="invalid task=None: must be a bitcomm.TaskConfig"):
        api.evaluate(lambda obs: obs, None)  # type: ignore[arg-type,return-value]


def test_commands_whose_time_is_torchs_take_threads(
    run_dir: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--threads` (default: the idle cores, or OMP_NUM_THREADS) on train, eval, analyze and variance: a command
    beside busy cores must not fight them with torch's own thread count."""
    from bitcomm.cli import build_parser
    from bitcomm.commands.flags import default_threads

    parser = build_parser()
    for argv in (["train"], ["eval", "RUN"], ["analyze"], ["variance", "RUN"]):
        assert parser.parse_args([*argv, "--threads", "3"]).threads == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert default_threads() is None  # torch reads the variable itself
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert 1 <= (default_threads() or 0) <= (os.cpu_count() or 1)

    before = torch.get_num_threads()
    try:
        assert main(["eval", str(run_dir), "--episodes", "100", "--seed", "5", "--threads", "1", "--json"]) == 0
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    ours = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    theirs = bitcomm("eval", str(run_dir), "--episodes", "100", "--seed", "5", "--json").stdout  # OMP_NUM_THREADS=1
    assert ours == json.loads(theirs.strip().splitlines()[-1])


@pytest.mark.parametrize("value", ["abc", "0", "-2", "1.5", "2,", "2,0"])
def test_an_omp_num_threads_openmp_cannot_read_is_one_error_line(
    value: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not the OpenMP runtime's own warning, then a run on threads it picked: every command refuses it, before work."""
    monkeypatch.setenv("OMP_NUM_THREADS", value)
    for argv in (["train", *TINY, "--episodes", "16"], ["baseline", "--episodes", "1"], ["eval", "RUN"]):
        assert main(argv) == 2
        assert capsys.readouterr().err.splitlines() == [
            f"bitcomm {argv[0]}: error: invalid OMP_NUM_THREADS={value!r}: must be a positive integer (torch's "
            "threads); unset, --threads or the idle cores choose them"
        ]


def test_an_omp_num_threads_openmp_reads_is_left_to_torch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`3`, ` 3`, OpenMP's list by nesting level `2,1`; an empty one is no setting, and OpenMP says nothing."""
    from bitcomm.commands.flags import check_omp_threads

    for value in ("3", " 3", "+3", "2,1", "2, 1"):
        monkeypatch.setenv("OMP_NUM_THREADS", value)
        check_omp_threads()
        assert os.environ["OMP_NUM_THREADS"] == value
    run = tmp_path / "run"
    env = {**ENV, "OMP_NUM_THREADS": " "}
    argv = ["train", *TINY, "--episodes", "16", "--quiet", "--eval-episodes", "0", "--out", str(run)]
    command = [sys.executable, "-m", "bitcomm", *argv]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert "torch threads: " in done.stdout and "OMP_NUM_THREADS" not in done.stdout


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--estimator", "foo"],
        ["eval", "RUN", "--threads", "0"],
        ["train", "--episodes", "0"],
        ["train", "--lr", "-1"],
        ["eval", "{missing}"],
        ["eval", "{corrupt}"],
        ["eval", "{corrupt_run}"],
        ["train", "--workers", "3"],  # sync mode has no workers
        ["train", "--conv-stride", "1"],  # the default recipe's encoder has no convolutions
        ["train", "--coords"],  # nor coordinate planes to add to them
        ["train", "--foo", "1"],  # an unknown flag, named with its command
    ],
)
def test_bad_input_is_one_line(argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    corrupt = tmp_path / "x.safetensors"
    corrupt.write_bytes(b"not a checkpoint at all")
    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
    (run / "latest.json").write_text(json.dumps({"checkpoint": "ckpt_000000016.safetensors"}))
    (run / "ckpt_000000016.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}")
    paths = {"missing": tmp_path / "nope", "corrupt": corrupt, "corrupt_run": tmp_path / "run"}
    argv = [a.format(**paths) for a in argv] + ["--out", str(tmp_path / "out")] * (argv[0] == "train")
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("argv", "dest", "typed"),
    [
        (["train"], "out", "--out=~/runs/a"),
        (["compare"], "out", "--out=~/study"),
        (["render", "--policy", "oracle"], "out", "--out=~/episode.gif"),
        (["export", "run"], "onnx", "--onnx=~/policy.onnx"),
    ],
)
def test_a_tilde_in_an_output_flag_is_the_home_folder(
    argv: list[str], dest: str, typed: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The shell leaves `--out=~/runs/a` as typed; a folder named `~` in the working directory is not what was
    meant (and `rm -rf ~` is how one would remove it)."""
    from bitcomm.cli import build_parser

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args([*argv, typed])
    assert getattr(args, dest) == tmp_path / "home" / typed.partition("~/")[2]


def test_a_recipe_s_coordinate_planes_stand_down_with_an_encoder_that_has_no_convolutions() -> None:
    """`supervised` adds coordinate planes to its convolutions; with `--encoder marginals` they would do nothing,
    so the run records them off rather than a setting it does not use."""
    from bitcomm.learn.config import make_train_config

    assert make_train_config("supervised").model.coords
    assert not make_train_config("supervised", encoder="marginals").model.coords
    assert make_train_config(encoder="conv", coords=True).model.coords


def test_a3c_trains_shared_weights_and_resumes(tmp_path: Path) -> None:
    from bitcomm.learn.learner import Learner

    out = tmp_path / "a3c"
    args = ["train", *TINY, "--mode", "a3c", "--workers", "2", "--quiet", "--eval-episodes", "0", "--out", str(out)]
    bitcomm(*args, "--episodes", "64", "--anneal-lr")  # the schedule reaches the workers' shared optimizers
    assert [int(r["episodes"]) for r in rows(out)] == [16, 32, 48, 64]
    cfg = tiny_config(mode="a3c", episodes=64, anneal_lr=True)
    torch.manual_seed(cfg.seed)
    init = Learner(cfg).policy.state_dict()
    trained = weights(out)
    changed = [k for k, v in init.items() if not torch.equal(trained[f"policy.{k}"], v)]
    assert changed, "no update reached the shared weights"
    bitcomm(*args, "--episodes", "96", "--resume")
    assert [int(r["episodes"]) for r in rows(out)][-2:] == [80, 96]
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["episodes"] == 96
