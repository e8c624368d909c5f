"""`bitcomm compare --env` on a tiny wrapped env: the study's files, the channel-cut control, a second call that
trains nothing, and one-line errors for options that do not apply.

The env is `SignalEnv` of test_env_learning: the listener earns 1 per episode only by reading the speaker's
message; without it, it is right half the time.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from tests.test_env_learning import BAD_ENVS, SPEC

from bitcomm.cli import main

STUDY = ["compare", "--env", SPEC, "--bits", "2", "--num-envs", "64", "--episodes", "2560", "--hidden", "32",
         "--lr", "3e-3", "--techniques", "improved-bitwise,no-comm", "--seeds", "1", "--jobs", "2",
         "--eval-episodes", "256"]  # fmt: skip


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("env-compare") / "study"
    assert main([*STUDY, "--out", str(out)]) == 0
    return out


def test_study_learns_to_talk_and_the_cut_control_shows_it(study: Path) -> None:
    summary = json.loads((study / "summary.json").read_text())
    assert summary["study"]["env"] == SPEC and summary["study"]["channel"]["bits"] == 2
    by_name = {c["name"]: c for c in summary["configurations"]}
    assert list(by_name) == ["improved-bitwise", "no-comm"]
    talking, alone = by_name["improved-bitwise"], by_name["no-comm"]
    assert talking["sampled"]["mean_team_return"]["mean"] > 0.9
    assert talking["cut"]["mean_team_return"]["mean"] < 0.7  # the same policy, every message dropped
    assert alone["sampled"]["mean_team_return"]["mean"] < 0.7  # trained without the channel
    assert talking["runs"][0]["episodes"] == 2560 and talking["runs"][0]["folder"] == "runs/improved-bitwise/seed0"


def test_study_writes_curves_table_and_plot(study: Path) -> None:
    with (study / "curves.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert {r["configuration"] for r in rows} == {"improved-bitwise", "no-comm"}
    assert {"team_return_rolling", "team_return", "episode_length"} <= set(rows[0])
    assert max(int(r["episodes"]) for r in rows) == 2560
    table = (study / "table.md").read_text()
    assert "return, channel cut at evaluation" in table and "| improved-bitwise |" in table
    run = json.loads((study / "summary.json").read_text())["configurations"][0]["runs"][0]
    per_seed = " / ".join(f"{run[play]['mean_team_return']:.3f}" for play in ("sampled", "greedy", "cut"))
    assert "## Per seed" in table and f"| improved-bitwise | {per_seed} |" in table
    assert "## Rolling team return along the budget" in table
    assert (study / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_second_call_trains_nothing(study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = (study / "summary.json").read_text()
    assert main([*STUDY, "--out", str(study)]) == 0
    assert "2 runs, all finished and evaluated" in capsys.readouterr().out
    assert (study / "summary.json").read_text() == before


def test_report_trains_nothing(study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = [*STUDY, "--out", str(study), "--report"]
    argv[argv.index("--seeds") + 1] = "2"  # seed 1 of each technique was never trained: left out
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "--report: 2 runs not finished, left out" in out and "trained" not in out
    assert not list(study.glob("runs/*/seed1"))
    assert "1 of 2 seeds x 2,560 episodes (finished runs)" in (study / "table.md").read_text()
    assert main([*STUDY, "--out", str(study)]) == 0  # the study's own files again, for the tests after this one


def test_a_folder_holding_another_study_is_refused(study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = [*STUDY, "--out", str(study)]
    argv[argv.index("--lr") + 1] = "1e-3"
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other lr" in err


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--size", "5"], "size"),
        (["--recipe", "paper"], "recipe"),
        (["--vary", "lr=1e-3,3e-3"], "vary"),
        (["--mode", "a3c"], "mode"),
        (["--seeds", "2", "--eval-seed", "1"], "eval-seed"),
        (["--episodes", "8", "--num-envs", "16"], "episodes"),  # below one batch, which every run would play
    ],
)
def test_options_that_do_not_apply_are_one_line(
    extra: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["compare", "--env", SPEC, *extra, "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err, err
    assert not (tmp_path / "s" / "runs").exists()


@pytest.mark.parametrize(("flags", "names"), BAD_ENVS)
def test_a_bad_env_is_one_line_before_any_run(
    flags: list[str], names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flags = [f for f in flags if f not in ("--messages", "onehot")]  # the study has one-hot runs anyway
    assert main(["compare", *flags, "--hidden", "16", "--seeds", "1", "--out", str(tmp_path / "s")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and names in err, (out, err)
    assert not (tmp_path / "s").exists()


def test_env_flags_without_env_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["compare", "--topology", "ring", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "topology" in err


def test_first_seed_moves_every_run_of_the_study(tmp_path: Path) -> None:
    from bitcomm.cli import build_parser
    from bitcomm.commands.compare import env_study
    from bitcomm.studies.env_compare import plan

    _, _, cfg = env_study(build_parser().parse_args([*STUDY, "--first-seed", "7", "--out", str(tmp_path / "s")]))
    assert [(r.configuration.technique, r.seed, r.train.seed, r.folder.name) for r in plan(cfg)] == [
        ("improved-bitwise", 7, 7, "seed7"),
        ("no-comm", 7, 7, "seed7"),
    ]
