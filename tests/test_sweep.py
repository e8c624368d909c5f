"""`bitcomm sweep`: one evaluation per (policy, parameter, value), CSV and PNG, noise costs steps."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.policies.source import PolicySource
from bitcomm.provenance import RECORDED
from bitcomm.studies.sweep import parse_param, run_sweep, with_param

TINY = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))


def test_parse_param() -> None:
    assert parse_param("act-fail-prob=0,0.1") == ("act_fail_prob", (0.0, 0.1))
    assert parse_param("act_delay=0,2") == ("act_delay", (0, 2))
    for bad in ("act_delay=0.5", "speed=1", "flip_prob", "flip_prob=x", "drop_prob=", "flip_prob=0,0.1,0"):
        with pytest.raises(ConfigError):
            parse_param(bad)
    assert with_param(TINY, "delay", 3).channel.delay == 3
    with pytest.raises(ConfigError):
        with_param(TINY, "flip_prob", 1.5)


def test_noise_costs_steps_and_zero_noise_is_the_base_task() -> None:
    params = {"act_fail_prob": (0.0, 0.4), "drop_prob": (0.0, 0.4), "flip_prob": (0.0, 0.2)}
    points = run_sweep([PolicySource("oracle")], TINY, params, episodes=200, seed=0)
    by = {(p.param, p.value): p.result for p in points}
    base = by[("act_fail_prob", 0.0)]
    assert by[("drop_prob", 0.0)] == base == by[("flip_prob", 0.0)]  # same episode set at every point
    for name in params:
        assert by[(name, params[name][1])].mean_episode_length > base.mean_episode_length


def test_cli_writes_csv_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sw"
    argv = ["sweep", "--policy", "oracle", "--policy", "random", "--size", "4", "--bits", "4", "--max-steps", "40",
            "--episodes", "50", "--param", "act_fail_prob=0,0.2", "--param", "act_delay=0,1,2"]  # fmt: skip
    assert main([*argv, "--out", str(out)]) == 0
    with (out / "sweep.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * (2 + 3)
    assert {r["policy"] for r in rows} == {"oracle", "random"}
    assert all(float(r["ci95_low"]) <= float(r["mean_episode_length"]) <= float(r["ci95_high"]) for r in rows)
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    record = json.loads((out / "provenance.json").read_text())  # what made the figure: flags, task, code, machine
    assert record["settings"]["seed"] == 0 and record["settings"]["task"]["env"]["max_steps"] == 40
    assert set(RECORDED) <= set(record)
    assert (out / "sweep.svg").read_text().startswith("<?xml")
    assert f"wrote {out / 'sweep.csv'}, {out / 'sweep.png'}, {out / 'sweep.svg'} and" in capsys.readouterr().out
    assert main(["sweep", "--param", "speed=1", "--out", str(out)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_parameter_given_twice_is_one_line_not_its_first_values_dropped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["sweep", "--policy", "oracle", "--size", "4", "--bits", "4", "--episodes", "10", "--out", str(tmp_path)]
    assert main([*argv, "--param", "flip_prob=0.1", "--param", "flip-prob=0.2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "invalid param=" in err and "each NAME at most once" in err
    assert not (tmp_path / "sweep.csv").exists()


def test_threads_flag_sets_torchs_threads(tmp_path: Path, threads, capsys: pytest.CaptureFixture[str]) -> None:
    """`--threads N` (as on eval): the points are played on N torch threads; 0 is one error line."""
    from bitcomm.commands import sweep as command

    threads.watch(command, "run_sweep")
    argv = ["sweep", "--policy", "oracle", "--size", "4", "--bits", "4", "--episodes", "10", "--param", "act_delay=0"]
    assert main([*argv, "--threads", str(threads.want), "--out", str(tmp_path / "sw"), "--json"]) == 0
    assert threads.seen == [threads.want]
    assert threads.zero_is_one_line("sweep", capsys)


def test_a_learned_policy_reads_the_same_at_every_point_of_its_own_task_as_bitcomm_eval_with_the_seed(
    tmp_path: Path,
) -> None:
    """Common random numbers hold for a sampling policy too: each point gets the sampling stream of `--seed`
    (not the last point's stream, carried on), so a point equal to the run's own task reads as
    `bitcomm eval RUN --seed S` does, wherever it stands in the sweep."""
    import torch

    from bitcomm.checkpoint import save_checkpoint
    from bitcomm.learn.config import make_train_config
    from bitcomm.policies.evaluation import evaluate_checkpoint
    from bitcomm.policies.networks import PolicyNet

    cfg = make_train_config("reinforced", TaskConfig(EnvConfig(size=4, max_steps=30), ChannelConfig(bits=4)))
    torch.manual_seed(0)
    run = tmp_path / "run"  # an untrained policy: it samples widely, so a stream carried on shows
    save_checkpoint(run, cfg.to_dict(), {"policy": PolicyNet(cfg.task, cfg.model).state_dict()}, 16, 1, state={})
    params = {"act_delay": (0,), "drop_prob": (0.0,), "flip_prob": (0.0,)}  # each the run's own task
    points = run_sweep([PolicySource("run", str(run))], cfg.task, params, episodes=40, seed=3)
    assert [p.result for p in points] == [evaluate_checkpoint(run, episodes=40, seed=3)] * 3


def test_a_table_stopped_as_it_is_written_keeps_the_one_before(tmp_path: Path) -> None:
    """`sweep`, `variance` or `scaling` stopped (Ctrl-C, SIGTERM) while it wrote its CSV left half a table; it is
    written whole or not at all."""
    from bitcomm.studies.tables import write_rows_csv

    path = write_rows_csv([{"value": 1}], ["value"], tmp_path / "sweep.csv")
    before = path.read_text()

    def stopped_midway() -> Iterator[dict[str, int]]:
        yield {"value": 2}
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_rows_csv(stopped_midway(), ["value"], path)
    assert path.read_text() == before and [p.name for p in tmp_path.iterdir()] == ["sweep.csv"]
