"""`bitcomm compare` on a tiny grid: every file there and well formed, a second call trains nothing and writes
the same files, an evaluation gains a play it lacks, `--report` trains nothing and reports the finished runs, a
partial run is resumed, `--vary` makes the product of configurations, bad input is one line."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError
from bitcomm.learn.run_folder import machine_label
from bitcomm.provenance import RECORDED, machine
from bitcomm.studies.compare import (
    CHOICES,
    CompareConfig,
    Curve,
    along_budget_markdown,
    budget_marks,
    execute,
    first_below,
    first_logged,
    machines_sentence,
    plan,
    read_curve,
    recorded_config,
    rolling_at_episodes,
    run_status,
    seconds_phrase,
    task_sentence,
)
from bitcomm.studies.tables import task_title

TINY = ["--size", "3", "--bits", "4", "--max-steps", "16", "--num-envs", "16", "--epochs", "1", "--minibatches", "1",
        "--eval-episodes", "50"]  # fmt: skip
TINY_OPTIONS = "epochs=1, minibatches=1, num_envs=16"
"""How table.md's title names TINY's learning options (the task's are in the line below it)."""
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
OUTPUTS = ("curves.csv", "curves.png", "curves.svg", "table.md", "summary.json")


def bitcomm(*args: str) -> subprocess.CompletedProcess:
    out = subprocess.run(
        [sys.executable, "-m", "bitcomm.cli", *args], capture_output=True, text=True, env=ENV, timeout=120
    )
    assert out.returncode == 0, out.stderr
    return out


def strict_json(path: Path) -> Any:
    def refuse(name: str) -> None:
        raise AssertionError(f"{name} in {path}")

    return json.loads(path.read_text(), parse_constant=refuse)


def intervals(node: Any) -> list[dict[str, Any]]:
    """Every {mean, ci95, n} of a summary."""
    if isinstance(node, dict):
        found = [node] if {"mean", "ci95", "n"} <= set(node) else []
        return found + [i for v in node.values() for i in intervals(v)]
    if isinstance(node, list):
        return [i for v in node for i in intervals(v)]
    return []


def markdown_tables(text: str) -> list[list[list[str]]]:
    """Every table of a Markdown text: its rows (header first, the separator left out) as lists of cells."""
    tables: list[list[list[str]]] = []
    previous = ""
    for line in text.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            if not previous.startswith("|"):
                tables.append([])
            tables[-1].append([c.strip() for c in line.strip("|").split(" | ")])
        previous = line
    return tables


def curves(out: Path) -> list[dict[str, str]]:
    with (out / "curves.csv").open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("compare") / "study"
    return out, bitcomm("compare", *TINY, "--episodes", "64", "--seeds", "2", "--jobs", "2", "--out", str(out)).stdout


def test_study_writes_every_file_well_formed(study: tuple[Path, str]) -> None:
    out, stdout = study
    assert stdout.count("trained to 64 episodes") == len(CHOICES) * 2
    rows = curves(out)
    assert {(r["configuration"], r["seed"]) for r in rows} == {(t, s) for t in CHOICES for s in ("0", "1")}
    assert all(math.isfinite(float(v)) for r in rows for k, v in r.items() if k not in ("configuration", "technique"))
    assert max(int(r["episodes"]) for r in rows) == 64
    assert (out / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "curves.svg").read_text().startswith("<?xml")

    summary = strict_json(out / "summary.json")
    assert summary["study"]["episodes"] == 64 and summary["study"]["seeds"] == 2
    record = strict_json(out / "provenance.json")  # what made the study's files: flags, code, machine, command
    assert record["settings"]["episodes"] == 64 and set(RECORDED) <= set(record)
    oracle = summary["oracle"][""]["mean_episode_length"]
    assert 1 < oracle < 16
    assert [c["name"] for c in summary["configurations"]] == list(CHOICES)
    for c in summary["configurations"]:
        assert c["communication"] == (c["technique"] != "no-comm") and c["oracle_mean_episode_length"] == oracle
        assert [r["seed"] for r in c["runs"]] == [0, 1]
        assert c["seeds"] == 2
        for r in c["runs"]:
            assert r["episodes"] == 64 and r["sampled"]["episodes"] == r["greedy"]["episodes"] == 50
            assert r["cut"]["episodes"] == 50  # the same policy with every message dropped
            assert set(r["reached"]) == {"2x", "1.15x"}
            config = json.loads((out / r["folder"] / "config.json").read_text())
            assert config["seed"] == r["seed"] and config["task"]["env"]["size"] == 3
            assert config["task"]["channel"]["drop_prob"] == (1.0 if c["technique"] == "no-comm" else 0.0)
            assert (config["estimator"], config["model"]["messages"]) == (c["estimator"], c["messages"])
        assert c["sampled"]["mean_episode_length"]["n"] == c["wall_s"]["n"] == 2
    found = intervals(summary["configurations"])
    assert len(found) >= len(CHOICES) * 7
    assert all(i["ci95"][0] <= i["mean"] <= i["ci95"][1] for i in found)

    text = (out / "table.md").read_text()
    main_table, per_seed, along = markdown_tables(text)
    assert [row[0] for row in main_table] == ["configuration", "oracle", *CHOICES]
    assert all(len(row) == len(main_table[0]) for row in main_table)
    assert main_table[0][1] == "seeds" and {row[1] for row in main_table[2:]} == {"2"}
    cut_column = main_table[0].index("length, channel cut at evaluation")
    for row, c in zip(main_table[2:], summary["configurations"], strict=True):
        assert row[cut_column].startswith(f"{c['cut']['mean_episode_length']['mean']:.2f} ± ")
    # the title names the learning options the command set away from the recipe (TINY's), so two studies differ
    assert text.startswith(f"# bitcomm compare: reinforced recipe ({TINY_OPTIONS}), 2 seeds x 64 episodes\n")
    here = machine_label(machine())
    assert all(r["machines"] == [here] for c in summary["configurations"] for r in c["runs"])
    assert f"Every run ran on one machine ({here})." in text
    assert "| " + " | ".join(main_table[0]) + " |" in stdout  # the main table is printed

    by_name = {c["name"]: c for c in summary["configurations"]}
    assert per_seed[0] == ["configuration", "seed 0", "seed 1"]
    for name, *cells in per_seed[1:]:
        for run, text_cell in zip(by_name[name]["runs"], cells, strict=True):
            sampled, greedy, cut = (run[play]["mean_episode_length"] for play in ("sampled", "greedy", "cut"))
            assert text_cell.startswith(f"{sampled:.2f} ({greedy:.1f}; {cut:.1f}); 2x: ") and "; 1.15x: " in text_cell

    assert summary["study"]["episode_marks"] == [16, 32, 48, 64]  # an eighth, 8, is before the first batch of 16
    assert along[0] == ["configuration", *(f"{e} episodes" for e in (16, 32, 48, 64))]
    for name, *cells in along[1:]:
        at_end = by_name[name]["rolling_at_episodes"][-1]
        assert at_end["mean"] == pytest.approx(
            np.mean([r["final_rolling_episode_length"] for r in by_name[name]["runs"]])
        )
        assert len(cells) == 4 and cells[-1].startswith(f"{at_end['mean']:.2f} ± ")


def test_second_call_trains_nothing_and_rewrites_the_same_files(study: tuple[Path, str]) -> None:
    out, _ = study
    before = {name: (out / name).read_bytes() for name in OUTPUTS}
    checkpoints = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/seed*/checkpoints/latest.json")}
    evaluations = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/seed*/evaluation.json")}
    assert len(checkpoints) == len(evaluations) == len(CHOICES) * 2
    res = bitcomm("compare", *TINY, "--episodes", "64", "--seeds", "2", "--out", str(out), "--json")
    assert "10 runs, all finished and evaluated" in res.stderr and "trained" not in res.stderr
    assert json.loads(res.stdout) == strict_json(out / "summary.json")
    assert {name: (out / name).read_bytes() for name in OUTPUTS} == before
    assert {p: p.stat().st_mtime_ns for p in checkpoints} == checkpoints
    assert {p: p.stat().st_mtime_ns for p in evaluations} == evaluations


def test_an_evaluation_gains_the_plays_it_lacks_and_keeps_the_others(study: tuple[Path, str], tmp_path: Path) -> None:
    """An evaluation.json written before the channel-cut play existed: the next call measures that play alone."""
    out = tmp_path / "study"
    shutil.copytree(study[0], out)
    path = out / "runs" / "improved-bitwise" / "seed0" / "evaluation.json"
    record = json.loads(path.read_text())
    del record["cut"]
    record["sampled"]["mean_episode_length"] = 99.0  # a mark: kept, not measured again
    path.write_text(json.dumps(record))
    res = bitcomm("compare", *TINY, "--episodes", "64", "--seeds", "2", "--out", str(out))
    assert "1 to go" in res.stdout and "improved-bitwise seed 0: evaluated" in res.stdout
    again = json.loads(path.read_text())
    assert again["sampled"]["mean_episode_length"] == 99.0 and again["cut"]["episodes"] == 50
    assert {k: v for k, v in again.items() if k != "cut"} == record


def test_report_trains_nothing_and_reports_the_finished_runs(study: tuple[Path, str], tmp_path: Path) -> None:
    """A study whose no-comm has one finished seed of three, the others two: `--report` reports what is there."""
    out = tmp_path / "study"
    shutil.copytree(study[0], out)
    shutil.rmtree(out / "runs" / "no-comm" / "seed1")
    res = bitcomm("compare", *TINY, "--episodes", "64", "--seeds", "3", "--report", "--out", str(out), "--json")
    assert "--report: 6 runs not finished, left out" in res.stderr and "trained" not in res.stderr
    assert not (out / "runs" / "no-comm" / "seed1").exists() and not list(out.glob("runs/*/seed2"))
    summary = json.loads(res.stdout)
    assert summary["study"]["report"] and summary["study"]["seeds"] == 3
    assert {c["name"]: c["seeds"] for c in summary["configurations"]} == {
        **{t: 2 for t in CHOICES if t != "no-comm"},
        "no-comm": 1,
    }
    full = strict_json(study[0] / "summary.json")["configurations"][0]  # standard-onehot, both seeds finished
    assert all(summary["configurations"][0][k] == full[k] for k in ("sampled", "greedy", "cut", "reached", "wall_s"))
    text = (out / "table.md").read_text()
    assert text.startswith(f"# bitcomm compare: reinforced recipe ({TINY_OPTIONS}), 1-2 of 3 seeds x 64 episodes "
                           "(finished runs)\n")  # fmt: skip
    assert "| no-comm | 1 |" in text


def test_later_seeds_trained_elsewhere_join_the_study(study: tuple[Path, str], tmp_path: Path) -> None:
    """`--first-seed F --seeds S` trains seeds F..F+S-1 into the study's layout (a study split across machines, or
    one whose later seeds are added on another), and a report over all the seeds reads them with the others."""
    out = tmp_path / "study"
    shutil.copytree(study[0], out)
    added = bitcomm("compare", *TINY, "--episodes", "64", "--techniques", "improved-bitwise", "--seeds", "1",
                    "--first-seed", "2", "--jobs", "1", "--out", str(out), "--json")  # fmt: skip
    assert added.stderr.count("trained to 64 episodes") == 1 and "improved-bitwise seed 2" in added.stderr
    assert json.loads((out / "runs" / "improved-bitwise" / "seed2" / "config.json").read_text())["seed"] == 2
    summary = json.loads(added.stdout)
    assert (summary["study"]["seeds"], summary["study"]["first_seed"]) == (1, 2)
    assert [r["seed"] for c in summary["configurations"] for r in c["runs"]] == [2]
    assert "1 seed (2..2) x 64 episodes" in (out / "table.md").read_text().splitlines()[0]
    report = json.loads(bitcomm("compare", *TINY, "--episodes", "64", "--seeds", "3", "--report", "--out", str(out),
                                "--json").stdout)  # fmt: skip
    assert {c["name"]: [r["seed"] for r in c["runs"]] for c in report["configurations"]} == {
        **{t: [0, 1] for t in CHOICES if t != "improved-bitwise"},
        "improved-bitwise": [0, 1, 2],
    }
    # the evaluation seed may be any seed outside the training range, below it included
    runs = plan(CompareConfig(out=tmp_path, techniques=("no-comm",), seeds=2, first_seed=3, eval_seed=1))
    assert [(r.seed, r.train.seed, r.folder.name) for r in runs] == [(3, 3, "seed3"), (4, 4, "seed4")]


def test_report_of_a_folder_without_finished_runs_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["compare", *TINY, "--episodes", "64", "--seeds", "2", "--report", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"invalid out={str(tmp_path)!r}" in err and "no finished run" in err
    assert not list(tmp_path.iterdir())


def test_vary_makes_the_product_of_configurations(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "noise"
    args = ["--techniques", "improved-bitwise", "--vary", "flip-prob=0,0.1", "--episodes", "32", "--seeds", "1"]
    assert main(["compare", *TINY, *args, "--jobs", "1", "--out", str(out)]) == 0
    names = ["improved-bitwise flip_prob=0", "improved-bitwise flip_prob=0.1"]
    assert {(r["configuration"], r["flip_prob"]) for r in curves(out)} == set(zip(names, ("0", "0.1"), strict=True))
    summary = strict_json(out / "summary.json")
    assert [c["name"] for c in summary["configurations"]] == names
    assert set(summary["oracle"]) == {"flip_prob=0", "flip_prob=0.1"}
    noisy = json.loads((out / "runs" / "improved-bitwise_flip_prob=0.1" / "seed0" / "config.json").read_text())
    assert noisy["task"]["channel"]["flip_prob"] == 0.1
    stdout = capsys.readouterr().out
    assert all(f"| {n} |" in stdout for n in names)

    # the product: techniques x every varied option's values, learning and task options alike
    task = TaskConfig(EnvConfig(size=3), ChannelConfig(bits=4))
    vary = {"lr": (1e-3, 3e-4), "flip_prob": (0.0, 0.05, 0.1)}
    runs = plan(CompareConfig(out=tmp_path, techniques=("standard-onehot", "no-comm"), seeds=1, task=task, vary=vary))
    assert len(runs) == 2 * 2 * 3
    assert {(r.configuration.technique, r.train.lr, r.train.task.channel.flip_prob) for r in runs} == {
        (t, lr, f) for t in ("standard-onehot", "no-comm") for lr in vary["lr"] for f in vary["flip_prob"]
    }
    assert all(r.train.task.channel.drop_prob == (r.configuration.technique == "no-comm") for r in runs)


def test_partial_run_is_resumed_and_another_run_is_refused(tmp_path: Path) -> None:
    import torch

    torch.set_num_threads(1)
    task = TaskConfig(EnvConfig(size=3, max_steps=16), ChannelConfig(bits=4))
    common = dict(out=tmp_path, techniques=("improved-onehot",), seeds=1, eval_episodes=20, task=task)
    short, = plan(CompareConfig(**common, episodes=32, learning={"num_envs": 16}))  # fmt: skip
    assert execute(short, 20, 1000) == "new"
    full, = plan(CompareConfig(**common, episodes=48, learning={"num_envs": 16}))  # fmt: skip
    assert execute(full, 20, 1000) == "resume" and execute(full, 20, 1000) == "done"
    with (full.folder / "metrics.csv").open() as f:
        assert [int(r["episodes"]) for r in csv.DictReader(f)] == [16, 32, 48]
    other, = plan(CompareConfig(**common, episodes=48, learning={"num_envs": 16, "lr": 0.01}))  # fmt: skip
    with pytest.raises(ConfigError, match="lr"):
        execute(other, 20, 1000)


def test_a_run_a_stopping_study_never_began_leaves_no_folder_and_the_study_again_trains_it(tmp_path: Path) -> None:
    """A study stopped between its runs: its worker, given the next run, starts none (`_stopping`), but it had made
    that run's folder first, and the study left it empty. No folder is made for it now; the study again trains it."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    import torch

    from bitcomm.studies.compare import _init_worker

    torch.set_num_threads(1)
    task = TaskConfig(EnvConfig(size=3, max_steps=16), ChannelConfig(bits=4))
    common = dict(out=tmp_path, techniques=("improved-onehot",), seeds=1, task=task, episodes=32)
    (run,) = plan(CompareConfig(**common, learning={"num_envs": 16}))
    ctx = multiprocessing.get_context("spawn")
    stopping = ctx.Value("b", 1, lock=False)  # the study is stopping its runs
    with ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker, initargs=(os.getpid(), stopping)) as pool:
        with pytest.raises(KeyboardInterrupt):
            pool.submit(execute, run, 20, 1000).result(timeout=120)
    assert list(tmp_path.iterdir()) == []
    assert execute(run, 20, 1000) == "new" and (run.folder / "evaluation.json").is_file()


def test_a_runs_folder_made_for_it_goes_when_it_stops_before_writing_anything(tmp_path: Path) -> None:
    """A run stopped as it began (its lock taken, nothing written) leaves no folder, nor those made above it; one that
    wrote a file, and a folder that was there before, stay."""
    from bitcomm.run_lock import run_lock
    from bitcomm.studies.compare import made_for_the_run

    study = tmp_path / "study"
    study.mkdir()
    with pytest.raises(KeyboardInterrupt), made_for_the_run(study / "runs" / "a" / "seed0"):
        with run_lock(study / "runs" / "a" / "seed0"):
            raise KeyboardInterrupt
    assert list(study.iterdir()) == []
    with pytest.raises(KeyboardInterrupt), made_for_the_run(study / "runs" / "a" / "seed1"):
        (study / "runs" / "a" / "seed1" / "config.json").write_text("{}")
        raise KeyboardInterrupt
    assert [p.name for p in (study / "runs" / "a" / "seed1").iterdir()] == ["config.json"]


def test_a_folder_holding_a_run_of_the_other_kind_or_no_run_s_config_is_one_line(tmp_path: Path) -> None:
    """A grid study and a study on a wrapped env share the layout runs/<technique>/seed<k>: either one pointed at the
    other's --out ended in a KeyError traceback ('task', 'channel') reading the other's config.json."""
    from bitcomm.learn.config import TrainConfig
    from bitcomm.learn.env_config import EnvTrainConfig

    run, = plan(CompareConfig(out=tmp_path, techniques=("improved-bitwise",), seeds=1))  # fmt: skip
    (run.folder / "checkpoints").mkdir(parents=True)
    (run.folder / "checkpoints" / "latest.json").write_text('{"checkpoint": "ckpt_000000064.safetensors"}')
    config = run.folder / "config.json"
    config.write_text(json.dumps({"env": "pkg.mod:make", "channel": {"bits": 2}, "seed": 0}))
    with pytest.raises(ConfigError, match=r"holds a run on a wrapped env \(pkg.mod:make\), not one of this study"):
        run_status(run)
    config.write_text(json.dumps(run.train.to_dict()))
    assert isinstance(recorded_config(run.folder, TrainConfig), TrainConfig)
    with pytest.raises(ConfigError, match="holds a run of the grid task, not one of this study"):
        recorded_config(run.folder, EnvTrainConfig)
    config.write_text('{"seed": 0, "task": 3}')
    with pytest.raises(ConfigError, match=r"invalid config=.*: not a run's config \(KeyError"):
        run_status(run)


def test_the_table_names_the_machines_whose_seconds_it_mixes() -> None:
    def summary(*runs: list[str]) -> dict[str, Any]:
        return {"configurations": [{"runs": [{"machines": m} for m in runs]}]}

    assert machines_sentence(summary(["A, 2 cores"], ["A, 2 cores"])) == "Every run ran on one machine (A, 2 cores)."
    mixed = machines_sentence(summary(["A, 2 cores"], ["B, 16 cores"], ["B, 16 cores", "A, 2 cores"]))
    assert mixed.startswith("The runs ran on 2 machines (A, 2 cores: 2 runs; B, 16 cores: 2 runs)")
    assert "seconds compare only between runs of one machine" in mixed
    assert "do not record their machines" in machines_sentence(summary(["unrecorded"], ["unrecorded"]))


def test_the_figure_names_the_task_less_what_its_panels_vary() -> None:
    """curves.png's title named the base task's grid and K alone: a study of 3 agents with bit flips read as the
    paper's task, and one varying bits=3,4 was titled "K = 7" above both panels."""
    task = TaskConfig(EnvConfig(size=4, n_agents=3), ChannelConfig(bits=4, delay=2, flip_prob=0.05))
    assert task_title(task) == "4x4 grid, 3 agents, K = 4, delay 2, flip 0.05, drop 0"
    assert task_title(task, {"bits": (3, 4), "drop_prob": (0, 0.1)}) == "4x4 grid, 3 agents, delay 2, flip 0.05"
    # table.md named the base value of a varied option too: "3 agents ...; varied agents: 3, 4"
    study = {"task": task.to_dict(), "vary": {"agents": (3, 4)}}
    assert task_sentence(study) == "4x4 grid, K = 4, delay 2, flip 0.05, drop 0; varied agents: 3, 4"


def test_the_legend_names_the_oracle_that_only_a_later_panel_draws(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """curves.png's legend was the first panel's: a study varying bits=1,4 on a 3x3 grid (1 bit cannot name a cell, so
    that panel has no oracle) drew the oracle's dashed line in the second panel and never named it."""
    from types import SimpleNamespace

    from bitcomm.studies import compare

    cfg = CompareConfig(out=tmp_path, techniques=("improved-bitwise",), seeds=1, task=TaskConfig(EnvConfig(size=3)),
                        vary={"bits": (1, 4)})  # fmt: skip
    runs = compare.plan(cfg)
    steps = np.array([16.0, 32.0])
    curves = {r.folder: Curve(steps, steps / 16, np.array([20.0, 9.0]), steps, -steps) for r in runs}
    oracle = {"bits=1": None, "bits=4": SimpleNamespace(mean_episode_length=3.0)}
    drawn: list[Any] = []
    monkeypatch.setattr(compare, "save_figure", lambda fig, path: drawn.append(fig))
    compare.plot_curves(runs, curves, cfg, oracle, tmp_path / "curves.png")  # type: ignore[arg-type]
    legend = drawn[0].axes[0].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["improved-bitwise (1 seed)", "oracle"]


def test_time_to_a_level_is_the_first_batch_below_it() -> None:
    steps = np.array([16.0, 32.0, 48.0])
    curve = Curve(steps, np.array([1.0, 2.5, 4.0]), np.array([20.0, 9.0, 5.0]), steps, -steps)
    assert first_below(curve, 10.0) == {"episodes": 32, "wall_s": 2.5}
    assert first_below(curve, 5.0) is None


def test_a_level_at_or_above_the_training_cut_is_not_timed(tmp_path: Path) -> None:
    """A rolling length of episodes cut at 16 steps is below 16 from the first batch on: a run whose messages are all
    dropped "reached 2x the oracle" at its first batch where the oracle waits 8 steps for its goal (2x is over 16).
    Such a level is reported as not timed, in summary.json and both tables; a level below the cut still is."""
    out = tmp_path / "out"
    argv = ["compare", *TINY, "--delay", "8", "--techniques", "no-comm", "--seeds", "1", "--episodes", "16"]
    assert main([*argv, "--jobs", "1", "--out", str(out)]) == 0
    (c,) = json.loads((out / "summary.json").read_text())["configurations"]
    assert 2 * c["oracle_mean_episode_length"] >= 16 > 1.15 * c["oracle_mean_episode_length"]
    assert c["reached"]["2x"] == {"seeds": 0, "of": 1, "episodes": None, "wall_s": None, "above_cut": 16}
    assert c["runs"][0]["reached"]["2x"] is None
    assert "above_cut" not in c["reached"]["1.15x"]
    table = (out / "table.md").read_text()
    assert "| above the 16-step training cut | " in table and "; 2x: above the cut; 1.15x: " in table


@pytest.mark.parametrize(
    ("text", "says"),
    [
        (None, "No such file"),
        ("", "no rows"),
        ("episodes,wall_s\n", "no rows"),
        ("episodes,wall_s\n16,1.0\n", "no column 'charts/episode_length_rolling'"),
        ("{header}\n16,1.0,20,20,-5\n32,2.0,1", "line 3 has fewer cells than the header"),
        ("{header}\n16,1.0,20,20,-5,9\n", "line 2 has more cells than the header"),
        ("{header}\n16,1.0,twenty,20,-5\n", "could not convert string to float: 'twenty'"),
    ],
)
def test_a_damaged_metrics_csv_is_one_line_naming_the_run(tmp_path: Path, text: str | None, says: str) -> None:
    """A report reads every run's metrics.csv: one missing, empty, cut mid-line (a copy that stopped short) or
    holding a word names the run and what is wrong with it, rather than a traceback."""
    header = "episodes,wall_s,charts/episode_length_rolling,charts/episode_length,charts/team_return"
    if text is not None:
        (tmp_path / "metrics.csv").write_text(text.format(header=header))
    with pytest.raises(ConfigError, match=f"invalid run={str(tmp_path)!r}: metrics.csv") as err:
        read_curve(tmp_path)
    assert says in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "metrics.csv").write_text(f"{header}\n16,1.0,20,20,-5\n32,2.0,9,8,-4\n")
    assert read_curve(tmp_path).length_rolling.tolist() == [20.0, 9.0]


def test_the_tables_read_every_curve_at_fractions_of_the_budget_as_the_plot_draws_it() -> None:
    assert budget_marks(200_000) == [25_000, 50_000, 100_000, 150_000, 200_000]
    assert budget_marks(4) == [1, 2, 3, 4]  # an eighth of 4 episodes is read at the first
    steps = np.array([16.0, 32.0, 48.0])
    curve = Curve(steps, np.array([1.0, 2.5, 4.0]), np.array([20.0, 9.0, 5.0]), steps, -steps)
    assert rolling_at_episodes(curve, 40, "length_rolling") == pytest.approx(7.0)  # between two batches
    assert rolling_at_episodes(curve, 8, "length_rolling") == 20.0  # before the first batch: its value
    assert rolling_at_episodes(curve, 64, "length_rolling") == 5.0


def test_a_tiny_budget_is_read_only_from_the_first_logged_batch_on() -> None:
    """8 episodes in batches of 4 were read at "1 episodes" and "2 episodes", where no run had logged anything
    (every value there was the first batch's): the marks start at the runs' latest first logged batch, and a
    header says "1 episode" where a batch of one episode was logged."""
    steps = np.array([4.0, 8.0])
    curves = [Curve(steps, steps, steps, steps, steps), Curve(steps - 3, steps, steps, steps, steps)]
    assert budget_marks(8, first_logged(curves)) == [4, 6, 8]
    assert budget_marks(8, 16) == [16]  # one batch of 16 for a budget of 8: read where it was logged
    summary = {"study": {"episode_marks": [1, 2, 25_000]}, "configurations": [{"name": "x", "rolling_at_episodes": []}]}
    assert "| configuration | 1 episode | 2 episodes | 25,000 episodes |" in along_budget_markdown(summary, "r", ".3f")


@pytest.mark.parametrize(
    "argv",
    [
        ["--vary", "speed=1,2"],
        ["--vary", "flip_prob"],
        ["--vary", "lr=fast"],
        ["--vary", "epochs=1.5"],
        ["--vary", "lr=-1,0.001"],
        ["--vary", "flip_prob=0,2"],
        ["--vary", "lr=1e-3", "--vary", "lr=1e-4"],
        ["--techniques", "improved-bitwise,telepathy"],
        ["--eval-seed", "1", "--seeds", "2"],
        ["--eval-seed", "6", "--seeds", "2", "--first-seed", "5"],
        ["--first-seed", "4294967295", "--seeds", "2"],
        ["--seeds", "0"],
        ["--episodes", "50"],  # below one batch of 128, which every run would play
        ["--episodes", "64", "--vary", "num_envs=32,128"],
    ],
)
def test_bad_input_is_one_line(argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["compare", "--size", "3", "--bits", "4", *argv, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


def test_an_interrupt_of_the_parent_alone_stops_the_running_runs(tmp_path: Path) -> None:
    """An alarm or a Ctrl-C that reaches only the parent (as a scheduler sends it) ends the study, its running runs
    stopped after the batch they are on and saved rather than waited for to their budget, so the next call resumes
    them. (Ended at once, as they were, runs a minute long lost all they had played before their first checkpoint.)"""
    import multiprocessing

    folders = [tmp_path / "runs" / "improved-bitwise" / f"seed{seed}" for seed in (0, 1)]
    start = time.monotonic()

    def logged(folder: Path) -> bool:
        return (folder / "metrics.csv").is_file() and len((folder / "metrics.csv").read_text().splitlines()) > 1

    def interrupt(*_: object) -> None:  # once both runs train (starting them takes seconds on a busy machine)
        if time.monotonic() - start > 60 or all(logged(f) for f in folders):
            signal.setitimer(signal.ITIMER_REAL, 0)  # once: a second interrupt ends the runs at once
            raise KeyboardInterrupt

    runs = ["--episodes", "40000", "--seeds", "2", "--techniques", "improved-bitwise"]  # a minute or more each
    argv = ["compare", "--size", "4", "--bits", "4", *runs, "--jobs", "2", "--out", str(tmp_path)]
    previous = signal.signal(signal.SIGALRM, interrupt)
    signal.setitimer(signal.ITIMER_REAL, 1.0, 0.5)
    try:
        code = main(argv)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert code != 0 and time.monotonic() - start < 90
    deadline = time.monotonic() + 20  # and no run trains on behind it (it would hold the parent at its exit)
    while multiprocessing.active_children() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not multiprocessing.active_children()
    for folder in folders:  # each saved the batch it was on, long before its first timed checkpoint
        assert 0 < json.loads((folder / "checkpoints" / "latest.json").read_text())["episodes"] < 40000


def test_sigterm_interrupts_a_study_as_ctrl_c_does() -> None:
    """`kill PID` of a study, or a scheduler's time limit, used to end it (and, with it, its runs) at once; while the
    study waits on its runs SIGTERM is an interrupt, so the runs save their batch first (`stop_runs`), exit 143."""
    from bitcomm.stop_signals import Stopped, sigterm_interrupts

    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    with pytest.raises(Stopped) as stopped, sigterm_interrupts():
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("not reached: the handler raises as the signal arrives")
    assert stopped.value.exit_code == 143
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


GRID = ["--policy", "oracle", "--size", "4", "--bits", "4"]


@pytest.mark.parametrize(
    ("argv", "first_step", "output"),
    [
        (["sweep", *GRID, "--param", "flip_prob=0,0.1"], "parse_param", ("--out", "out")),
        (["variance", "runs/some-run"], "variance_config", ("--out", "out")),
        (["analyze", *GRID], "source_from_args", ("--out", "out")),
        (["render", *GRID], "source_from_args", ("--out", "out.gif")),
        (["export", "runs/some-run"], "_check_output", ("--onnx", "out.onnx")),
    ],
    ids=["sweep", "variance", "analyze", "render", "export"],
)
def test_sigterm_as_a_command_starts_stops_it_as_ctrl_c_does(
    argv: list[str],
    first_step: str,
    output: tuple[str, str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
) -> None:
    """`timeout`, `kill PID` or a scheduler's time limit while `sweep`, `variance`, `analyze`, `render` or `export`
    started (or worked) killed it at once, by SIGTERM's default, where Ctrl-C stops it in one line (and a file being
    written, whole or not at all, leaves no temporary behind); SIGTERM now does too, exit 143. Here the signal comes
    with the command's first step."""
    import importlib

    def sigterm(*args: Any) -> None:
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # it would end the command, and pytest with it
            raise AssertionError("SIGTERM would have killed the command at once")
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(importlib.import_module(f"bitcomm.commands.{argv[0]}"), first_step, sigterm)
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    flag, name = output
    assert main([*argv, flag, str(tmp_path / name)]) == 143
    assert capsys.readouterr().err == f"bitcomm {argv[0]}: interrupted\n"
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


def test_a_runs_stop_reaches_the_study_as_it_was_raised(tmp_path: Path) -> None:
    """A study's run sends its `Stopped` back to the study through a pipe. Rebuilt from its message (the signal's
    name) it failed to unpickle there, which broke the pool: the study ended every other run at once, saved or not,
    and the resource tracker warned of leaked semaphores."""
    import pickle

    from bitcomm.stop_signals import Stopped

    back = pickle.loads(pickle.dumps(Stopped(signal.SIGTERM, tmp_path / "ckpt.safetensors", 48)))
    assert isinstance(back, Stopped) and back.exit_code == 143 and str(back) == "SIGTERM"
    assert back.checkpoint == tmp_path / "ckpt.safetensors" and back.episodes == 48


def test_timeouts_second_copy_is_dropped_however_soon_after_the_first_it_comes(monkeypatch: pytest.MonkeyPatch) -> None:
    """`timeout` signals the study, then its process group. The guard that drops the group's copy was put in place
    only once the first signal's `Stopped` had reached the study's clean-up: now and then the copy came first, and the
    study then waited, for good, on a run that nobody had asked to stop (CI, once). It is in place from the start."""
    from bitcomm import stop_signals
    from bitcomm.stop_signals import Stopped, repeats_count_once, sigterm_interrupts

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with sigterm_interrupts(), repeats_count_once():
            with pytest.raises(Stopped):
                signal.raise_signal(signal.SIGTERM)
            signal.raise_signal(signal.SIGTERM)  # the group's copy, before any clean-up began: dropped
            signal.raise_signal(signal.SIGINT)  # Ctrl-C as well, within the same moment
            monkeypatch.setattr(stop_signals, "REPEAT_S", 0.0)
            with pytest.raises(KeyboardInterrupt):  # one later stops at once
                signal.raise_signal(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_timeout_of_a_study_saves_the_batch_each_run_is_on(tmp_path: Path, signum: signal.Signals) -> None:
    """`timeout -s INT` (or plain `timeout`, SIGTERM) signals the study, then its process group: the second signal
    ended the runs at once while the study waited for them to save, and the group's SIGTERM killed them outright.
    Either way they lost all they had played since their last checkpoint; now each saves the batch it is on."""
    folder = tmp_path / "runs" / "improved-bitwise" / "seed0"
    argv = [*TINY, "--episodes", "100000", "--seeds", "1", "--techniques", "improved-bitwise"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "bitcomm.cli", "compare", *argv, "--jobs", "1", "--out", str(tmp_path)],
        env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as in a terminal, even under CI
    )  # fmt: skip
    deadline = time.monotonic() + 90
    while not (folder / "metrics.csv").is_file() or len((folder / "metrics.csv").read_text().splitlines()) < 3:
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr and proc.stderr.read()
        time.sleep(0.05)
    proc.send_signal(signum)  # what `timeout` does: the command, then its process group
    os.killpg(proc.pid, signum)
    _, err = proc.communicate(timeout=90)
    assert proc.returncode == 128 + signum, err
    played = int((folder / "metrics.csv").read_text().splitlines()[-1].split(",")[1])
    saved = json.loads((folder / "checkpoints" / "latest.json").read_text())["episodes"]
    assert "stopped after" in err and saved == played
    assert "Traceback" not in err and "leaked" not in err, err  # the run's `Stopped` came back whole, the pool intact


CTRL_C_AT_START = """
import os, signal, sys
from concurrent.futures import ProcessPoolExecutor

submit = ProcessPoolExecutor.submit


def submit_then_ctrl_c(self, *args, **kwargs):
    future = submit(self, *args, **kwargs)  # which starts the worker for it
    os.killpg(0, signal.SIGINT)  # Ctrl-C while that worker imports bitcomm
    return future


ProcessPoolExecutor.submit = submit_then_ctrl_c
if __name__ == "__main__":
    from bitcomm.cli import main
    from bitcomm.studies import compare

    compare.STOP_GRACE_S = 600.0  # a run that did not stop is waited for far longer than the test waits

    sys.exit(main(sys.argv[1:]))
"""
"""`bitcomm compare` with a Ctrl-C to its process group as its worker starts."""


def test_ctrl_c_as_a_studys_workers_start_stops_it_quietly_and_at_once(tmp_path: Path) -> None:
    """A Ctrl-C while a study's worker started printed the worker's traceback (KeyboardInterrupt in an import), and,
    once the worker ignored Ctrl-C but before it took its run, the study's own request to stop was lost: the run
    trained on until the study ended it, unsaved, `STOP_GRACE_S` (a minute) later. It now starts no run."""
    script = tmp_path / "ctrl_c_at_start.py"
    script.write_text(CTRL_C_AT_START)
    argv = [*TINY, "--episodes", "100000", "--seeds", "1", "--techniques", "improved-bitwise"]
    proc = subprocess.Popen(
        [sys.executable, str(script), "compare", *argv, "--jobs", "1", "--out", str(tmp_path / "study")],
        env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as in a terminal, even under CI
    )  # fmt: skip
    try:
        _, err = proc.communicate(timeout=120)  # long before the study would end the run at once
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130 and "Traceback" not in err and "leaked" not in err, err
    assert err.strip().splitlines()[-1] == "bitcomm compare: interrupted"
    assert not (tmp_path / "study" / "runs" / "improved-bitwise" / "seed0" / "checkpoints").exists()


def test_a_quick_studys_equal_wall_clock_is_not_read_as_0_seconds() -> None:
    """The table's last column is each run's rolling length at the quickest run's training time; a study of seconds
    (a smoke test, a tiny grid) headed it "after 0 s"."""
    assert [seconds_phrase(s) for s in (0.3, 0.04, 9.5, 110.4, 1234.4)] == [
        "0.3 s", "0.04 s", "9.5 s", "110 s", "1,234 s"
    ]  # fmt: skip
