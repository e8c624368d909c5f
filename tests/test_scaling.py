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
    assert "wrote" in capsys.readouterr().out
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
