"""`bitcomm variance`: the standard and improved estimators compared at the fixed policies of a tiny run.

The run: 3x3 grid, K = 2 bits, episodes of at most 20 steps, gamma = 0.5, two batches of 16 episodes and a
checkpoint after each, so it has two stages.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.learn.config import make_train_config
from bitcomm.learn.estimators import Advantages, policy_gradient_loss
from bitcomm.learn.learner import Learner
from bitcomm.learn.rollout import Collector
from bitcomm.learn.run import train
from bitcomm.provenance import RECORDED
from bitcomm.studies.variance import (
    PARTS,
    Moments,
    VarianceConfig,
    VarianceRow,
    cosine,
    gradient_parts,
    load_stage,
    markdown_table,
    measure_stage,
    parse_stages,
    run_of,
    select_stages,
    variance_lines,
)

TINY = TaskConfig(EnvConfig(size=3, max_steps=20), ChannelConfig(bits=2))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("variance") / "run"
    cfg = make_train_config("reinforced", TINY, num_envs=16, episodes=32, gamma=0.5, checkpoint_seconds=0)
    train(cfg, out, progress=False)
    return out


def test_stages_pick_checkpoints_kept_along_the_run(run_dir: Path) -> None:
    names = lambda files: [f.name for f in files]  # noqa: E731
    both = ["ckpt_000000016.safetensors", "ckpt_000000032.safetensors"]
    assert names(select_stages(run_dir, parse_stages("all"))) == both
    assert names(select_stages(run_dir, parse_stages("latest"))) == both[1:]
    assert names(select_stages(run_dir, parse_stages("spread:2"))) == both
    assert names(select_stages(run_dir, parse_stages("spread:9"))) == both
    assert names(select_stages(run_dir, parse_stages("32,16"))) == both[::-1]
    file = run_dir / "checkpoints" / both[0]
    assert select_stages(file, "all") == [file]
    for bad in ("first", "spread:0", "spread:x", "16,x", ""):
        with pytest.raises(ConfigError, match="stages"):
            parse_stages(bad)
    with pytest.raises(ConfigError, match="episodes 16, 32"):
        select_stages(run_dir, (20,))


def test_log_probs_are_those_of_acting(run_dir: Path) -> None:
    """Recomputed with gradients, the log-probabilities of the sampled moves and messages equal the
    ones the collector recorded while acting: the estimates differentiate the policy that played."""
    stage = load_stage(run_dir)
    learner = Learner(stage.config)
    learner.policy.load_state_dict(stage.weights)
    policy = learner.policy
    ro = Collector(TINY, 8).collect(policy, __import__("numpy").random.SeedSequence(3), torch.Generator())
    logp_move, logp_message = learner.log_probs(ro)
    v = ro.valid
    torch.testing.assert_close(logp_move[v], ro.logp_move[v])
    torch.testing.assert_close(logp_message[v], ro.logp_message[v])
    assert logp_move.requires_grad and (logp_move[~v] == 0).all()

    # the parts split the whole estimate: message + action = -grad of the full policy-gradient loss
    gen = torch.Generator().manual_seed(0)
    adv = Advantages(*(torch.randn(ro.moves.shape, generator=gen) for _ in range(2)), torch.zeros(v.shape))
    parts = gradient_parts(policy, logp_move, logp_message, adv, v)
    grads = torch.autograd.grad(policy_gradient_loss(logp_move, logp_message, adv, v), list(policy.parameters()),
                                allow_unused=True)  # fmt: skip
    whole = -torch.cat([(torch.zeros_like(p) if g is None else g).flatten()
                        for p, g in zip(policy.parameters(), grads, strict=True)])  # fmt: skip
    torch.testing.assert_close(parts["message"] + parts["action"], whole)
    torch.testing.assert_close(parts["total"], whole)
    assert parts["message"].norm() > 0 and parts["action"].norm() > 0


def test_moments_give_the_trace_of_the_covariance() -> None:
    samples = torch.randn(50, 7, generator=torch.Generator().manual_seed(0)) * torch.arange(1, 8) + 3
    m = Moments()
    for row in samples:
        m.add(row)
    assert m.trace_cov == pytest.approx(float(samples.double().var(0).sum()), rel=1e-9)
    torch.testing.assert_close(m.mean, samples.double().mean(0))
    a = torch.tensor([1.0, 0.0])
    assert cosine(a, torch.tensor([2.0, 0.0])) == pytest.approx(1)
    assert cosine(a, torch.tensor([0.0, 3.0])) == pytest.approx(0)
    assert cosine(a, -a) == pytest.approx(-1)


def test_improved_message_gradient_has_lower_variance(run_dir: Path) -> None:
    """Paper III-C at a policy of the tiny run: the message part of the improved estimate varies less.

    The improved message advantage gamma * (Q_{t+1} - V2(s_{t+1}, a_{t+1}^{-x})) leaves out what the standard
    one, Q_t - V1(s_t, a_t^{-j}, m), carries: the reward of step t, the sender's own actions at t and t + 1,
    the next state. With gamma = 0.5 those near steps are a large share of the return's variance, so the gap
    is clear with 32 batches: measured ratios 0.15 to 0.37 (0.26 here) over three runs x five or more seeds
    (at gamma = 0.95 on this 20-step task the ratio is about 0.8, too close to 1 for 32 batches to resolve
    reliably). An improved estimator that forgot its gamma^delay would sit near 1 (x 1/gamma^2), so 0.5 has power.
    Both estimators are unbiased for the same gradient: their mean action parts point the same way.
    """
    rows = {r.part: r for r in measure_stage(load_stage(run_dir), VarianceConfig(batches=32, num_envs=16,
                                                                                  fit_batches=30))}  # fmt: skip
    message, action = rows["message"], rows["action"]
    assert message.ratio < 0.5, f"message variance ratio improved/standard = {message.ratio:.3f}"
    assert action.cosine > 0.9, f"cosine of the mean action gradients = {action.cosine:.3f}"


def test_cli_writes_csv_markdown_png_and_json(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "var"
    quick = ["--batches", "6", "--num-envs", "8", "--fit-batches", "3", "--out", str(out)]
    assert main(["variance", str(run_dir), *quick, "--stages", "spread:3"]) == 0
    printed = capsys.readouterr()
    assert f"{run_dir}: spread:3 measures the 2 checkpoints it keeps" in printed.err.splitlines()
    with (out / "variance.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(int(r["episodes"]), r["part"]) for r in rows] == [(e, p) for e in (16, 32) for p in PARTS]
    for r in rows:
        figures = [float(r[k]) for k in ("var_standard", "var_improved", "ratio", "cosine", "norm_standard")]
        assert all(math.isfinite(x) for x in figures) and figures[0] > 0 and figures[1] > 0
        assert float(r["ratio"]) == pytest.approx(float(r["var_improved"]) / float(r["var_standard"]))
        assert -1 <= float(r["cosine"]) <= 1
    table = (out / "variance.md").read_text().splitlines()
    # the task in full: a title of grid, K and delay alone read a run whose messages all drop as one that talks
    assert table[0] == "# Gradient variance of the two estimators: 3x3 grid, 2 agents, K = 2, delay 1, flip 0, drop 0"
    assert sum(line.startswith("| 16 |") or line.startswith("| 32 |") for line in table) == 6
    assert (out / "variance.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "variance.svg").read_text().startswith("<?xml")
    assert f"{out / 'variance.png'}, {out / 'variance.svg'} and provenance.json" in printed.out  # every file it wrote
    record = json.loads((out / "provenance.json").read_text())  # what made the figure: flags, task, code, machine
    assert record["settings"]["seed"] == 0 and record["settings"]["task"]["env"]["size"] == 3
    assert set(RECORDED) <= set(record)

    # one stage, measured on the task with a longer message delay, as JSON
    assert main(["variance", str(run_dir), *quick, "--stages", "latest", "--delay", "2", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert [r["part"] for r in printed] == list(PARTS) and printed[0]["episodes"] == 32

    # bad input: one line, exit status 2
    assert main(["variance", str(run_dir), "--stages", "7", "--out", str(out)]) == 2
    assert main(["variance", str(run_dir), "--bits", "3", "--out", str(out)]) == 2
    assert capsys.readouterr().err.count("\n") == 2


def measured(checkpoint: str, episodes: int, part: str) -> VarianceRow:
    """A row as `measure_stage` makes one, with made-up figures."""
    return VarianceRow(episodes, part, 2.0, 1.0, 0.5, 0.9, 1.0, 1.0, 0.1, 0.1, 3, 6, 8, checkpoint)


def test_rows_of_several_runs_are_kept_apart_in_the_table_and_the_plot() -> None:
    stages = [(f"runs/{run}/checkpoints/ckpt_{e:09d}.safetensors", e) for run in ("a", "b") for e in (10, 20)]
    rows = [measured(f, e, part) for f, e in [*stages, ("loose.safetensors", 30)] for part in PARTS]
    assert [run_of(r) for r in rows[:: len(PARTS)]] == ["runs/a", "runs/a", "runs/b", "runs/b", "loose.safetensors"]
    table = markdown_table(rows).splitlines()
    assert "| run | episodes trained |" in "\n".join(table)
    per_run = [sum(line.startswith(f"| {run} | ") for line in table) for run in ("runs/a", "runs/b")]
    assert per_run == [2 * len(PARTS)] * 2
    lines = variance_lines(rows, "message")  # one line per run and estimator: stages of two runs never joined
    runs = ("runs/a", "runs/b", "loose.safetensors")
    assert [label for label, _, _ in lines] == [f"{e}: {run}" for run in runs for e in ("standard", "improved")]
    assert [x for x, _ in lines.values()] == [[10, 20]] * 4 + [[30]] * 2

    two = rows[: 4 * len(PARTS)]  # runs/a and runs/b: labelled without the folder they share
    assert [label for label, _, _ in variance_lines(two, "total")][::2] == ["standard: a", "standard: b"]
    one = rows[: 2 * len(PARTS)]  # one run: no run column, the estimators' names as labels
    assert "| run |" not in markdown_table(one)
    assert [label for label, _, _ in variance_lines(one, "action")] == ["standard", "improved"]


def test_cli_defaults_are_the_config_defaults() -> None:
    """The command writes its defaults out (to keep torch out of CLI start-up); they must be VarianceConfig's."""
    from bitcomm.cli import build_parser
    from bitcomm.commands.variance import variance_config

    assert variance_config(build_parser().parse_args(["variance", "RUN"])) == VarianceConfig()


def test_every_plateau_the_flag_takes_the_config_takes() -> None:
    """`--plateau` takes [0, 1] and said so, then `--plateau 1` was refused as "must be in [0, 1)" (1: stop at the
    first window the loss is compared on)."""
    from bitcomm.cli import build_parser
    from bitcomm.commands.variance import variance_config

    for value in ("0", "0.5", "1"):
        assert variance_config(build_parser().parse_args(["variance", "RUN", "--plateau", value])).plateau == float(
            value
        )
    with pytest.raises(ConfigError, match=r"invalid plateau=1.5: must be in \[0, 1\]"):
        VarianceConfig(plateau=1.5)


def test_a_checkpoint_named_twice_or_of_another_task_is_one_line(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A run given twice (or with one of its files) was measured twice, its rows printed twice; runs of different
    tasks were measured and titled, plotted and recorded in provenance.json as the last one's task."""
    other = tmp_path / "other"
    train(make_train_config("reinforced", TaskConfig(EnvConfig(size=4, max_steps=20), ChannelConfig(bits=2)),
                            num_envs=16, episodes=16, checkpoint_seconds=0), other, progress=False)  # fmt: skip
    latest = str(select_stages(run_dir, "latest")[0])
    quick = ["--stages", "latest", "--batches", "2", "--num-envs", "8", "--fit-batches", "1", "--out", str(tmp_path)]
    assert main(["variance", str(run_dir), latest, *quick]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"bitcomm variance: error: invalid RUN_OR_CHECKPOINT={latest!r}: {latest} is measured already; give each once"
    ]
    assert main(["variance", str(run_dir), str(other), *quick]) == 2
    mine = select_stages(other, "latest")[0]
    assert capsys.readouterr().err.strip().splitlines() == [
        f"bitcomm variance: error: invalid RUN_OR_CHECKPOINT='{mine}': its task (4x4 grid, 2 agents, K = 2, delay 1, "
        f"flip 0, drop 0) is not {latest}'s (3x3 grid, 2 agents, K = 2, delay 1, flip 0, drop 0); one table measures "
        "one task: run bitcomm variance once per task"
    ]
    assert not (tmp_path / "variance.csv").exists()
