"""`bitcomm scaling`: what the bitwise and one-hot message heads cost as the grid grows (paper III-A).

Counts are checked against the layer sizes worked out by hand; the run uses small grids (4x4, K = 4 and
6x6, K = 6) and the paper recipe's single-step update, timed once.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from bitcomm.cli import main
from bitcomm.errors import ConfigError
from bitcomm.policies.networks import ModelConfig
from bitcomm.provenance import RECORDED
from bitcomm.studies.scaling import ScalingConfig, ScalingRow, bits_for, learning_run, parse_sizes


def test_bits_name_every_cell() -> None:
    assert [bits_for(s) for s in (10, 16, 32, 64)] == [7, 8, 10, 12]  # the sizes
    assert [bits_for(s) for s in (2, 3, 4, 5, 6)] == [2, 4, 4, 5, 6]
    assert all(2 ** bits_for(s) >= s * s > 2 ** (bits_for(s) - 1) for s in range(2, 70))
    assert parse_sizes("4, 6") == (4, 6)
    for bad in ("4,x", ""):
        with pytest.raises(ConfigError, match="sizes"):
            parse_sizes(bad)
    with pytest.raises(ConfigError, match="sizes"):
        ScalingConfig(sizes=(1,))


def test_cli_small_sizes(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "sc"
    argv = ["scaling", "--sizes", "4,6", "--recipe", "paper", "--repeats", "1", "--out", str(out)]
    assert main(argv) == 0
    written = [out / name for name in ("scaling.csv", "scaling.md", "scaling.png", "scaling.svg", "provenance.json")]
    assert f"wrote {', '.join(map(str, written))}" in capsys.readouterr().out  # every file, nothing trained: no curves
    record = json.loads((out / "provenance.json").read_text())  # what made the tables: flags, code, machine
    assert record["settings"]["sizes"] == "4,6" and set(RECORDED) <= set(record)
    with (out / "scaling.csv").open() as f:
        rows = {(int(r["size"]), r["messages"]): r for r in csv.DictReader(f)}
    assert sorted(rows) == [(4, "bitwise"), (4, "onehot"), (6, "bitwise"), (6, "onehot")]
    m = ModelConfig()  # the paper recipe keeps the default widths; one input slot per agent (two agents)
    for size, k in ((4, 4), (6, 6)):
        bitwise, onehot = (rows[size, name] for name in ("bitwise", "onehot"))
        assert bitwise["final_episode_length"] == onehot["final_episode_length"] == ""  # not trained
        words = ("messages", "final_episode_length")
        n = {r["messages"]: {key: float(v) for key, v in r.items() if key not in words} for r in (bitwise, onehot)}
        # output size: linear in K for bitwise, 2^K for one-hot
        assert n["bitwise"]["bits"] == n["onehot"]["bits"] == k
        assert n["bitwise"]["message_outputs"] == k and n["onehot"]["message_outputs"] == 2**k
        assert n["onehot"]["policy_outputs"] - n["bitwise"]["policy_outputs"] == 2**k - k
        for name, outputs, reads in (("bitwise", k, k), ("onehot", 2**k, 2**k)):
            # message logits: a (hidden -> outputs) layer; message input: a (reads -> message_hidden) layer
            assert n[name]["message_head_params"] == (m.hidden + 1) * outputs
            assert n[name]["message_input_params"] == (reads + 1) * m.message_hidden
        extra = 2**k - k  # one-hot: that many more outputs (weights + bias each) and inputs (weights)
        assert n["onehot"]["policy_params"] - n["bitwise"]["policy_params"] == (m.hidden + 1 + m.message_hidden) * extra
        assert n["onehot"]["critic_v1_params"] - n["bitwise"]["critic_v1_params"] == m.message_hidden * extra
        assert n["onehot"]["critic_v2_params"] == n["bitwise"]["critic_v2_params"]  # V2 never reads messages
        for name in ("bitwise", "onehot"):
            r = n[name]
            assert r["param_bytes"] == 4 * (r["policy_params"] + r["critic_v2_params"])  # improved: policy + V2
            assert r["update_peak_bytes"] > 0 and 0 < r["update_seconds"] < 60 and r["batch_samples"] > 0
            assert all(math.isfinite(r[key]) for key in ("train_memory_gb", "update_seconds"))
    table = (out / "scaling.md").read_text()
    assert table.count("| 4x4 |") == 2 and table.count("| 6x6 |") == 2
    assert (out / "scaling.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "scaling.svg").read_text().startswith("<?xml")
    assert not (out / "runs").exists()  # --episodes 0: no training

    assert main([*argv[:-2], "--sizes", "3", "--out", str(tmp_path / "j"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert [(r["size"], r["messages"], r["message_outputs"]) for r in printed] == [(3, "bitwise", 4), (3, "onehot", 16)]
    assert all(r["final_episode_length"] is None for r in printed)


def test_learning_curves_at_a_fixed_budget(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`--episodes`: a real training run per size and head; its last rolling episode length lands in the row."""
    out = tmp_path / "sc"
    argv = ["scaling", "--sizes", "2", "--repeats", "1", "--episodes", "8", "--num-envs", "4", "--json"]
    assert main([*argv, "--out", str(out)]) == 0
    printed = {r["messages"]: r for r in json.loads(capsys.readouterr().out)}
    for name in ("bitwise", "onehot"):
        with (out / "runs" / f"2_{name}" / "metrics.csv").open() as f:
            last = list(csv.DictReader(f))[-1]
        assert printed[name]["episodes"] == int(last["episodes"]) == 8
        assert printed[name]["final_episode_length"] == pytest.approx(float(last["charts/episode_length_rolling"]))
    assert "not trained" not in (out / "scaling.md").read_text()
    assert (out / "scaling_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "scaling_curves.svg").read_text().startswith("<?xml")

    # called again, the finished runs are kept (it used to stop on "already holds a run (use --resume ...)", a flag
    # scaling lacks); with a larger budget they are resumed, not started again
    metrics = out / "runs" / "2_bitwise" / "metrics.csv"
    before = metrics.read_text()
    assert main([*argv, "--out", str(out)]) == 0
    assert metrics.read_text() == before
    budget = argv.index("--episodes") + 1
    assert main([*argv[:budget], "12", *argv[budget + 1 :], "--out", str(out)]) == 0
    assert {r["messages"]: r["episodes"] for r in json.loads(capsys.readouterr().out.splitlines()[-1])} == {
        "bitwise": 12,
        "onehot": 12,
    }
    with metrics.open() as f:
        assert [int(r["episodes"]) for r in csv.DictReader(f)] == [4, 8, 12]
    assert metrics.read_text().startswith(before)


def test_no_training_where_one_hot_would_not_fit(tmp_path: Path) -> None:
    row = ScalingRow(64, 12, "onehot", 4096, 4101, 0, 0, 0, 0, 0, 0, 0, 0.0, 1, train_memory_gb=20.0)
    scfg = ScalingConfig(sizes=(64,), episodes=1000, max_memory_gb=8.0)
    assert learning_run(row, scfg, tmp_path / "run") == row
    assert not (tmp_path / "run").exists()


def test_cli_defaults_are_the_config_defaults() -> None:
    """The command writes its defaults and choices out (to keep torch out of CLI start-up); they must agree."""
    from bitcomm.cli import build_parser
    from bitcomm.commands.scaling import scaling_config
    from bitcomm.learn.config import RECIPES
    from bitcomm.learn.estimators import ESTIMATORS

    parser = build_parser()
    assert scaling_config(parser.parse_args(["scaling"])) == ScalingConfig()
    for recipe in RECIPES:
        assert scaling_config(parser.parse_args(["scaling", "--recipe", recipe])).recipe == recipe
    for name in ESTIMATORS:
        assert scaling_config(parser.parse_args(["scaling", "--estimator", name])).estimator == name


def test_threads_flag_sets_torchs_threads_and_is_recorded(
    tmp_path: Path, threads, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--threads N`: the updates are timed on N torch threads and scaling.md says so (the update times depend
    on it: 2923.8 ms on torch's default threads beside a busy core against 84.7 ms on one); without the flag,
    OMP_NUM_THREADS when set (torch's own count, left alone); 0 is one error line."""
    import bitcomm.studies.scaling as study

    threads.watch(study, "run_scaling")
    want = threads.want
    argv = ["scaling", "--sizes", "2", "--repeats", "1", "--batch-episodes", "1", "--batch-steps", "2", "--json"]
    assert main([*argv, "--threads", str(want), "--out", str(tmp_path / "a")]) == 0
    assert threads.calls == threads.seen == [want]
    last = (tmp_path / "a" / "scaling.md").read_text().splitlines()[-1]
    assert last.startswith(f"Updates timed on {want} torch thread") and last.endswith("(--threads).")
    monkeypatch.setenv("OMP_NUM_THREADS", str(want))  # torch read it at start-up: left alone
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0
    assert threads.calls == [want] and threads.seen == [want, want]
    last = (tmp_path / "b" / "scaling.md").read_text().splitlines()[-1]
    assert last.startswith(f"Updates timed on {want} torch thread") and last.endswith("(OMP_NUM_THREADS).")
    assert threads.zero_is_one_line("scaling", capsys)


def test_repeated_sizes_are_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`--sizes 4,4` measured 4x4 twice and printed its rows twice; now refused, naming the repeated side."""
    for text in ("4,4", "4,6,04"):
        assert main(["scaling", "--sizes", text, "--out", str(tmp_path / "sc")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--sizes" in err and "grid side 4 is repeated" in err, err
    assert not (tmp_path / "sc").exists()
