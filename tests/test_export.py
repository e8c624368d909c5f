"""`bitcomm export --onnx`: onnxruntime's logits are PyTorch's, `OnnxController` plays as `Controller`
(greedy: the same actions; sampling: the same distributions), the file carries its card, `bitcomm deploy
--onnx` plays it over UDP as the simulator does, and bad input is one line with exit status 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from bitcomm.checkpoint import resolve, save_checkpoint
from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.envs.vec import VecGoalExchange
from bitcomm.errors import ConfigError
from bitcomm.policies.controller import Controller
from bitcomm.policies.networks import PolicyNet
from bitcomm.policies.onnx_export import export_onnx
from bitcomm.policies.onnx_policy import OnnxController, sidecar_path

TINY = TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=4))
# agent 0 hears agents 1 and 2: two input slots
TWO_SLOTS = TaskConfig(
    EnvConfig(size=5, n_agents=3, max_steps=16), ChannelConfig(bits=4, recipients=((2,), (0,), (0,)))
)
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def make_checkpoint(
    folder: Path, task: TaskConfig = TINY, messages: str = "bitwise", coords: bool = False, **model: Any
) -> Path:
    """A run folder with one checkpoint of an untrained policy, written by the trainer's own writer; `model`: other
    network settings than the `reinforced` recipe's."""
    from bitcomm.learn.config import make_train_config

    coord_planes = {"coords": True, "encoder": "conv"} if coords else {}  # coordinate planes serve convolutions
    cfg = make_train_config("reinforced", task, messages=messages, **coord_planes, **model)
    torch.manual_seed(0)
    net = PolicyNet(task, cfg.model)
    with torch.no_grad():  # larger weights than at initialisation: logits far apart, as after training
        for p in net.parameters():
            p.mul_(3.0)
    save_checkpoint(folder, cfg.to_dict(), {"policy": net.state_dict()}, episodes=16, batches=1, state={})
    return folder


def random_inputs(task: TaskConfig, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    S, K = task.env.size, task.channel.bits
    return rng.random((n, 2, S, S), dtype=np.float32), rng.integers(0, 2, (n, task.slots, K)).astype(np.float32)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(run folder, its exported .onnx) of a bitwise policy on the 4x4 task."""
    run = make_checkpoint(tmp_path_factory.mktemp("export") / "run")
    out = run.parent / "policy.onnx"
    export_onnx(Controller.load(run), out)
    return run, out


@pytest.mark.parametrize(
    ("messages", "coords", "task"),
    [("bitwise", False, TINY), ("onehot", False, TINY), ("bitwise", True, TINY), ("onehot", True, TWO_SLOTS)],
)
def test_onnx_logits_equal_pytorch(tmp_path: Path, messages: str, coords: bool, task: TaskConfig) -> None:
    controller = Controller.load(make_checkpoint(tmp_path / "run", task, messages, coords))
    export_onnx(controller, tmp_path / "policy.onnx")
    onnx = OnnxController.load(tmp_path / "policy.onnx")
    planes, received = random_inputs(task, 37)  # not the batch size of the export: the batch axis is dynamic
    move, message = onnx.logits(planes, received)
    with torch.no_grad():
        torch_move, torch_message = controller.policy(torch.from_numpy(planes), torch.from_numpy(received))
    out = task.channel.bits if messages == "bitwise" else 1 << task.channel.bits
    assert move.shape == (37, 5) and message.shape == (37, out)
    np.testing.assert_allclose(move, torch_move.numpy(), rtol=0, atol=1e-5)
    np.testing.assert_allclose(message, torch_message.numpy(), rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    "model",
    [
        {"encoder": "cells", "message_map": True, "message_reads": "all"},  # the cells encoder, a message map
        {"encoder": "marginals", "message_reads": "all", "plane_coords": False},  # the paper's message head
    ],
)
def test_onnx_logits_equal_pytorch_for_other_networks(tmp_path: Path, model: dict[str, Any]) -> None:
    controller = Controller.load(make_checkpoint(tmp_path / "run", TWO_SLOTS, **model))
    export_onnx(controller, tmp_path / "policy.onnx")
    onnx = OnnxController.load(tmp_path / "policy.onnx")
    planes, received = random_inputs(TWO_SLOTS, 37)
    with torch.no_grad():
        expected = controller.policy(torch.from_numpy(planes), torch.from_numpy(received))
    for got, want in zip(onnx.logits(planes, received), expected, strict=True):
        np.testing.assert_allclose(got, want.numpy(), rtol=0, atol=1e-5)
    planes = (planes > 0.5).astype(np.float32)  # acting takes 0/1 planes
    for a, b in zip(
        onnx.act(planes, received, greedy=True), controller.act(planes, received, greedy=True), strict=True
    ):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("messages", ["bitwise", "onehot"])
def test_greedy_actions_equal_the_controllers(tmp_path: Path, messages: str) -> None:
    run = make_checkpoint(tmp_path / "run", messages=messages)
    export_onnx(Controller.load(run), tmp_path / "policy.onnx")
    controller, onnx = Controller.load(run), OnnxController.load(tmp_path / "policy.onnx")
    env = VecGoalExchange(TINY, 64, seed=0)  # observations as the environment gives them (uint8)
    obs = env.observe()
    planes, received = obs.planes.reshape(-1, 2, 4, 4), obs.received.reshape(-1, 1, 4)
    received = np.random.default_rng(1).integers(0, 2, received.shape).astype(np.uint8)
    ours, theirs = onnx.act(planes, received, greedy=True), controller.act(planes, received, greedy=True)
    for a, b in zip(ours, theirs, strict=True):  # moves, then message bits
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    move, bits = onnx.act(planes[0], received[0], greedy=True)  # one agent: no batch axis
    assert move.shape == () and bits.shape == (4,) and bits.dtype == np.uint8
    with pytest.raises(ConfigError, match="expected"):
        onnx.act(planes[:, :, :3], received)
    for bad in (controller, onnx):  # a robot's 0.5 or NaN is one line from either, not a silent cast or read
        with pytest.raises(ConfigError, match=r"^invalid planes value 0\.5: every entry must be 0 or 1$"):
            bad.act(planes * 0.5, received)
        with pytest.raises(ConfigError, match=r"^invalid received_bits value nan: every entry must be 0 or 1$"):
            bad.act(planes, np.where(received == 1, np.nan, 0.0))


@pytest.mark.parametrize("messages", ["bitwise", "onehot"])
def test_sampling_follows_the_policy_distribution(tmp_path: Path, messages: str) -> None:
    run = make_checkpoint(tmp_path / "run", messages=messages)
    export_onnx(Controller.load(run), tmp_path / "policy.onnx")
    onnx = OnnxController.load(tmp_path / "policy.onnx", seed=3)
    planes, received = random_inputs(TINY, 1)
    planes = (planes > 0.5).astype(np.float32)  # act reads 0/1 planes, as the env gives them
    draws = 4000
    moves, bits = onnx.act(np.repeat(planes, draws, 0), np.repeat(received, draws, 0))
    move_logits, message_logits = (torch.from_numpy(x[0]) for x in onnx.logits(planes, received))
    p_move = torch.softmax(move_logits, -1).numpy()
    np.testing.assert_allclose(np.bincount(moves, minlength=5) / draws, p_move, atol=0.03)
    if messages == "bitwise":
        np.testing.assert_allclose(bits.mean(0), torch.sigmoid(message_logits).numpy(), atol=0.03)
    else:
        index = bits.astype(np.int64) @ (1 << np.arange(3, -1, -1))  # bit 0 most significant
        p_message = torch.softmax(message_logits, -1).numpy()
        np.testing.assert_allclose(np.bincount(index, minlength=16) / draws, p_message, atol=0.03)


def test_the_file_carries_its_card(exported: tuple[Path, Path]) -> None:
    run, out = exported
    onnx = OnnxController.load(out)
    card = json.loads(sidecar_path(out).read_text())
    assert card == onnx.metadata
    assert (card["size"], card["bits"], card["slots"], card["messages"], card["agents"]) == (4, 4, 1, "bitwise", 2)
    assert card["inputs"] == {"planes": ["N", 2, 4, 4], "received": ["N", 1, 4]}
    assert card["outputs"] == {"move_logits": ["N", 5], "message_logits": ["N", 4]}
    assert card["checkpoint"] == str((run / "checkpoints" / "ckpt_000000016.safetensors").resolve())
    assert card["episodes_trained"] == 16 and card["bitcomm_version"]
    assert onnx.task == TINY
    inputs = {i.name: i.shape for i in onnx.session.get_inputs()}
    assert inputs == {"planes": ["N", 2, 4, 4], "received": ["N", 1, 4]}


def test_the_card_names_its_checkpoint_wherever_export_ran(
    exported: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`bitcomm export run ...` typed in the run's parent wrote "run/checkpoints/...", which traces nowhere from the
    robot the card is copied to."""
    run, _ = exported
    monkeypatch.chdir(run.parent)
    assert main(["export", run.name, "--onnx", str(tmp_path / "p.onnx")]) == 0
    card = json.loads(sidecar_path(tmp_path / "p.onnx").read_text())
    assert Path(card["checkpoint"]).is_absolute() and Path(card["checkpoint"]).samefile(resolve(run))


def test_the_card_says_who_hears_whom_and_what_each_tensor_holds(tmp_path: Path) -> None:
    """A runtime without bitcomm (C++, a microcontroller) reads the wiring from the card, not from `task`'s defaults
    (observes and recipients are null there when left at them), and how to fill and read each tensor."""
    from bitcomm.envs.core import DCOL, DROW

    run = make_checkpoint(tmp_path / "run", TWO_SLOTS, "onehot")
    card = export_onnx(Controller.load(run), tmp_path / "policy.onnx")
    assert card["task"]["env"]["observes"] is None  # the ring default, which only bitcomm knows how to fill in
    assert card["observes"] == [1, 2, 0]
    assert card["recipients"] == [[2], [0], [0]]
    assert card["slot_senders"] == [[1, 2], [-1, -1], [0, -1]]  # agent 0 hears 1 and 2 (its two slots), 1 nobody
    assert card["slot_senders"] == TWO_SLOTS.slot_senders.tolist()
    assert card["move_deltas"] == [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]] == np.stack([DROW, DCOL], 1).tolist()
    assert set(card["encoding"]) == set(card["inputs"]) | set(card["outputs"])
    assert "most significant first" in card["encoding"]["message_logits"]
    on_file = json.loads(sidecar_path(tmp_path / "policy.onnx").read_text())
    assert (
        on_file["slot_senders"] == card["slot_senders"]
        and on_file == OnnxController.load(tmp_path / "policy.onnx").metadata
    )


def test_the_runtime_needs_no_torch(exported: tuple[Path, Path]) -> None:
    code = (
        "import sys, numpy as np; from bitcomm.policies.onnx_policy import OnnxController; "
        f"c = OnnxController.load({str(exported[1])!r}); "
        "print(c.act(np.zeros((2, 4, 4), np.uint8), np.zeros((1, 4), np.uint8))[1].shape, 'torch' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["(4,)", "False"]


def test_cli_exports_a_run_folder(exported: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    run, reference = exported
    out = tmp_path / "new" / "folder" / "cli.onnx"  # made, as `render --out` makes its folder
    assert main(["export", str(run), "--onnx", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    assert out.stat().st_size > 0 and sidecar_path(out).is_file()
    planes, received = random_inputs(TINY, 5)
    got = OnnxController.load(out).logits(planes, received)
    expected = OnnxController.load(reference).logits(planes, received)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)


def test_eval_of_the_exported_file_plays_greedily_as_its_run(
    exported: tuple[Path, Path], capsys: pytest.CaptureFixture
) -> None:
    """`bitcomm eval policy.onnx` measures what a robot will run; it was 'not a bitcomm checkpoint (SafetensorError:
    ...)'. Greedy play is the run's to the episode; the task flags are checked as for the run."""
    run, out = exported

    def measured(*argv: str) -> dict[str, Any]:
        assert main(["eval", *argv, "--greedy", "--episodes", "40", "--seed", "3", "--json"]) == 0
        return json.loads(capsys.readouterr().out)

    assert measured(str(out)) == measured(str(run))
    assert measured(str(out), "--flip-prob", "0.2") == measured(str(run), "--flip-prob", "0.2")
    assert main(["eval", str(out), "--episodes", "10"]) == 0  # sampled, from onnxruntime's own stream
    assert f"{out} (sampling): 10 episodes" in capsys.readouterr().out
    assert main(["eval", str(out), "--size", "5"]) == 2
    refusal = f"bitcomm eval: error: invalid size=5: ONNX {str(out)!r} was trained with size=4"
    assert capsys.readouterr().err.strip() == refusal


@pytest.mark.parametrize("policy", ["onnx", "run"])
def test_deploy_runs_the_exported_policy(exported: tuple[Path, Path], policy: str) -> None:
    """As exported, or from its run folder: each agent process then samples from a torch stream of its own."""
    from bitcomm.policies.evaluation import evaluate_checkpoint

    run, out = exported
    source = ["--onnx", str(out)] if policy == "onnx" else [str(run)]
    cmd = [sys.executable, "-m", "bitcomm.cli", "deploy", *source, "--greedy", "--episodes", "12",
           "--seed", "2", "--deadline-ms", "200", "--json", "--timeout", "60"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=90)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    # greedy and nothing lost on the wire: the ONNX agents over UDP, the ONNX policy in the simulator and
    # the torch policy it was exported from play the same episodes step for step (returns included)
    expected = evaluate_checkpoint(run, episodes=12, seed=2, greedy=True).to_dict()
    assert {key: result[key] for key in expected} == expected
    assert {key: result["simulator"][key] for key in expected} == expected
    assert result["network"]["missing"] == 0 and result["network"]["sent"] > 0


@pytest.mark.parametrize("seed", [-1, 1.5, "abc", True, 2**64])
def test_a_bad_seed_is_one_line_as_the_controllers(exported: tuple[Path, Path], seed: object) -> None:
    """numpy's ValueError or TypeError (-1, 1.5, "abc"), or a seed taken (True, 2**64), where `Controller` says
    what a seed is."""
    run, out = exported
    for load in (lambda: Controller.load(run, seed=seed), lambda: OnnxController.load(out, seed=seed)):  # type: ignore[arg-type]
        with pytest.raises(ConfigError, match=r"^invalid seed=.*: must be an integer in \[0, 4294967295\]$"):
            load()


def test_both_controllers_take_a_seed_sequence_or_none_for_fresh_entropy(exported: tuple[Path, Path]) -> None:
    """A fleet seeds its robots as `OnnxController` allowed and `Controller` refused ('invalid seed=None'): one
    `SeedSequence` spawned per robot, or None for the OS's entropy. A sequence seeds as the int it generates."""
    run, out = exported
    robot = np.random.SeedSequence(7).spawn(2)[1]
    as_int = int(robot.generate_state(1, np.uint32)[0])
    assert torch.equal(
        Controller.load(run, seed=robot).generator.get_state(), Controller.load(run, seed=as_int).generator.get_state()
    )
    fresh = [Controller.load(run, seed=None).generator.initial_seed() for _ in range(2)]
    assert fresh[0] != fresh[1]
    for seed in (robot, None):  # as it already took them
        OnnxController.load(out, seed=seed)


@pytest.mark.parametrize("threads", [0, -1, "2", 2.5, None, True, 10**9])
def test_bad_threads_are_one_line(exported: tuple[Path, Path], threads: object) -> None:
    """onnxruntime's TypeError ("2", 2.5, None), a count it took in silence (0, -1, True), or its MemoryError read
    as a file that is not an ONNX model (10**9), where the number of threads is what was wrong."""
    with pytest.raises(ConfigError, match=r"^invalid threads=.*: must be an integer in \[1, 1024\]$"):
        OnnxController.load(exported[1], threads=threads)  # type: ignore[arg-type]
    planes, received = random_inputs(TINY, 3)
    moves, _ = OnnxController.load(exported[1], threads=np.int64(2)).act(planes > 0.5, received)
    assert moves.shape == (3,)


def _bad_onnx(tmp_path: Path) -> Path:
    bad = tmp_path / "not.onnx"
    bad.write_bytes(b"not an onnx model")
    return bad


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["export", "{missing}", "--onnx", "{out}"], "checkpoint"),
        (["export", "{run}", "--onnx", "{bad}/p.onnx"], "not.onnx' is a file, not a folder"),  # named, not p.onnx
        (["export", "{run}", "--onnx", "{tmp}"], "onnx"),
        (["export", "{run}"], "--onnx"),
        (["export", "{run}", "--onnx", "{run}/checkpoints/ckpt_000000016.safetensors"], "checkpoints folder"),
        (["export", "{run}", "--onnx", "{run}/checkpoints/latest"], "checkpoints folder"),  # card: latest.json
        (["deploy", "--onnx", "{missing}"], "onnx"),
        (["deploy", "--onnx", "{bad}"], "onnx"),
        (["deploy", "--onnx", "{run}"], "is a folder; give the .onnx file"),  # not "no such file"
        (["deploy", "--onnx", "{out}", "--policy", "oracle"], "onnx"),
        (["deploy", "--onnx", "{reference}", "--size", "5"], "size"),
    ],
)
def test_bad_input_is_one_line(
    argv: list[str], named: str, exported: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    run, reference = exported
    paths = {"missing": tmp_path / "nope", "out": tmp_path / "p.onnx", "run": run, "tmp": tmp_path,
             "bad": _bad_onnx(tmp_path), "reference": reference}  # fmt: skip
    rc: int | str | None
    try:
        rc = main([a.format(**paths) for a in argv])
    except SystemExit as e:  # argparse
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert named in err
    assert not (tmp_path / "p.onnx").exists()
    assert Controller.load(run).info["episodes"] == 16  # the run is as it was


def test_a_folder_where_the_card_goes_is_refused_before_the_graph_is_written(
    exported: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """The graph was written, then the card failed, and the line blamed the graph's file ("invalid onnx='p.onnx':
    cannot be written (Is a directory)")."""
    (tmp_path / "p.onnx.json").mkdir()
    assert main(["export", str(exported[0]), "--onnx", str(tmp_path / "p.onnx")]) == 2
    assert f"its card would go to {str(tmp_path / 'p.onnx.json')!r}, which is a folder" in capsys.readouterr().err
    assert not (tmp_path / "p.onnx").exists()


def test_export_never_replaces_a_runs_config(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`--onnx RUN/config` would write its card to RUN/config.json: one line, and the run's record stays."""
    run = make_checkpoint(tmp_path / "run")
    record = '{"seed": 0, "versions": {}}\n'
    (run / "config.json").write_text(record)
    assert main(["export", str(run), "--onnx", str(run / "config")]) == 2
    assert "config.json" in capsys.readouterr().err
    assert (run / "config.json").read_text() == record and not (run / "config").exists()


def test_missing_onnxruntime_says_how_to_install(exported: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails as if not installed
    with pytest.raises(ConfigError, match=r"pip install bitcomm\[onnx\]"):
        OnnxController.load(exported[1])
