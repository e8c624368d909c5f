"""The README quotes `benchmarks/train_speed.py`: it must run as written and print what the README reads."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.policies.evaluation import evaluate
from bitcomm.policies.reference import OraclePolicy

ROOT = Path(__file__).resolve().parents[1]
TINY = "--modes sync --recipes reinforced --batches 1 --warmup 1 --num-envs 8 --threads 1 --single-pass"


def test_train_speed_times_the_default_recipe_and_its_single_pass_variant_and_ends_with_json() -> None:
    out = subprocess.run(
        [sys.executable, "benchmarks/train_speed.py", *TINY.split()],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    results = summary["results"]
    passes = {name: (r["passes"], r["gradient_steps_per_batch"]) for name, r in results.items()}
    assert passes == {"sync/reinforced": (4, 16), "sync/reinforced/single-pass": (1, 1)}
    for r in results.values():
        assert r["num_envs"] == 8 and r["batches"] == 1 and r["agent_steps"] > 0 and r["agent_steps_per_s"] > 0


def test_train_speed_times_another_task_and_head_and_refuses_a_bad_head_in_one_line() -> None:
    argv = [sys.executable, "benchmarks/train_speed.py", "--modes", "sync", "--recipes", "reinforced", "--batches", "1",
            "--num-envs", "4", "--threads", "1", "--size", "5", "--bits", "5", "--messages"]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([*argv, "onehot"], cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["task"] == "5x5, K=5, onehot" and summary["results"]["sync/reinforced"]["agent_steps"] > 0
    bad = subprocess.run([*argv, "morse"], cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert bad.returncode == 2 and "messages='morse'" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize(("item", "said"), [("num_envs=64", "give --num-envs"), ("sender_hidden=0", "sender-hidden=0")])
def test_train_speed_takes_learning_options_by_set_and_refuses_bad_ones_in_one_line(item, said) -> None:
    """`--set` reaches every learning option but those the script sets itself, which have their own flags."""
    argv = [sys.executable, "benchmarks/train_speed.py", "--modes", "sync", "--recipes", "reinforced", "--set", item]
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and said in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize(
    ("task", "has_divergence_row"),
    [(TaskConfig(), True), (TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4)), False)],
    ids=["10x10-7-bits", "4x4-4-bits"],
)
def test_ablation_rows_are_single_changes_that_build_valid_configs(task: TaskConfig, has_divergence_row: bool) -> None:
    """Every row of `benchmarks/ablation.py` is a config the library accepts; the rows between the two recipes
    each change one option (or one group) in which the recipes differ on the task, and the last is the target
    itself. Where every word names a goal the recipe has no divergence, so no row turns it on."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from ablation import GROUPS, OBSERVED_ONLY, rows
    from bitcomm.learn.config import make_train_config, recipe_values

    for base, target in (("paper", "reinforced"), ("reinforced", "paper")):
        plan = rows(base, target, task)
        assert plan[0] == (base, {}) and plan[-1][0] == target
        b, t = recipe_values(base, task), recipe_values(target, task)
        assert set(plan[-1][1]) == {k for k in t if b.get(k) != t[k]}
        assert ("message_divergence" in dict(plan)) is has_divergence_row
        for name, change in plan[1:-1]:  # minibatches follow a batch made smaller than them, the observed head
            coupled = {"minibatches", *(["message_reads"] if name in OBSERVED_ONLY else [])}  # an option needing it
            assert set(GROUPS.get(name, (name,))) <= set(change) <= {*GROUPS.get(name, (name,)), *coupled}
        for _, change in plan:
            make_train_config(base, task, **change)


def test_every_recipe_names_the_same_options() -> None:
    """The ablation compares recipes key by key: an option one recipe leaves to the config's default would be
    missing from the rows, and a row set "to paper" would keep the default recipe's value of it."""
    from bitcomm.learn.recipes import RECIPES

    names = {name: set(options) for name, options in RECIPES.items()}
    assert all(keys == names["reinforced"] for keys in names.values()), names


def test_ablation_runs_a_row_and_resumes_from_its_result(tmp_path: Path) -> None:
    argv = [sys.executable, "benchmarks/ablation.py", "--size", "3", "--bits", "4", "--minutes", "0.002", "--chunk",
            "16", "--threads", "1", "--only", "mode", "--out", str(tmp_path)]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    assert "| mode | mode=sync |" in first.stdout and (tmp_path / "mode" / "result.json").is_file()
    again = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert again.stdout == first.stdout  # the kept result, not a new run
    marked = subprocess.run([*argv, "--marks", "16,1000000"], cwd=ROOT, capture_output=True, text=True, env=env,
                            timeout=300)  # fmt: skip
    row = next(line for line in marked.stdout.splitlines() if line.startswith("| mode |"))
    assert "rolling at 16 / 1,000,000 episodes |" in marked.stdout and row.endswith(" / — |"), marked.stdout
    assert float(row.split("|")[-2].split("/")[0]) > 0  # read from the row's metrics.csv at 16 episodes
    for bad_marks in ("16,x", "0"):
        refused = subprocess.run([*argv, "--marks", bad_marks], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert refused.returncode == 2 and "--marks" in refused.stderr.strip().splitlines()[-1]
    bad = subprocess.run([*argv[:-2], "--only", "nosuch"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "nosuch" in bad.stderr.strip().splitlines()[-1]


def test_an_annealing_ablation_row_needs_and_uses_a_horizon(tmp_path: Path) -> None:
    """A row that decays its rates is refused in one line without --max-episodes; with it, the row's run
    anneals over exactly that many episodes and the budget is recorded with the row's result."""
    argv = [sys.executable, "benchmarks/ablation.py", "--base", "reinforced", "--target", "paper", "--size", "3",
            "--bits", "4", "--minutes", "1", "--chunk", "16", "--threads", "1", "--only", "reinforced",
            "--out", str(tmp_path)]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    refused = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=60)
    assert refused.returncode == 2 and "--max-episodes" in refused.stderr.strip().splitlines()[-1]
    done = subprocess.run([*argv, "--max-episodes", "32"], cwd=ROOT, capture_output=True, text=True, env=env,
                          timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    saved = json.loads((tmp_path / "reinforced" / "result.json").read_text())
    assert saved["settings"]["max_episodes"] == 32
    config = json.loads((tmp_path / "reinforced" / "seed0" / "config.json").read_text())
    assert config["anneal_lr"] and config["anneal_episodes"] == 32


def test_solve_asks_for_the_horizon_of_an_annealing_recipe() -> None:
    argv = [sys.executable, "benchmarks/solve.py", "--size", "3", "--bits", "4"]
    refused = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--max-episodes" in refused.stderr.strip().splitlines()[-1]


def train_tiny_run(run: Path | str, *options: str) -> None:
    """`bitcomm train` of a 3x3, 4-bit run of 16-step episodes, one thread, no closing evaluation, plus `options`:
    the run a benchmark that reads run folders is tested on."""
    argv = [sys.executable, "-m", "bitcomm.cli", "train", "--size", "3", "--bits", "4", "--max-steps", "16",
            "--num-envs", "16", "--eval-episodes", "0", "--quiet", "--threads", "1", "--out", str(run),
            *options]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    assert subprocess.run(argv, cwd=ROOT, capture_output=True, env=env, timeout=120).returncode == 0


def test_greedy_split_plays_a_run_four_ways(tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = str(tmp_path / "run")
    train_tiny_run(run, "--episodes", "32", "--epochs", "1", "--minibatches", "1")
    out = subprocess.run([sys.executable, "benchmarks/greedy_split.py", run, "--episodes", "20"], cwd=ROOT,
                         capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    rows = [line for line in out.stdout.splitlines() if line.startswith(("| sampled", "| greedy"))]
    assert [r.split(" | ")[:2] for r in rows] == [["| sampled", "sampled"], ["| greedy", "greedy"],
                                                  ["| greedy", "sampled"], ["| sampled", "greedy"]]  # fmt: skip
    total = [int(line.split()[-3]) for line in out.stdout.splitlines() if line.startswith("greedy episodes cut at")]
    assert len(total) == 1 and out.stdout.count("at the step limit: ") == 1 and " of 20" in out.stdout

    def counted(table: str, column: int) -> int:  # a census table's episodes, summed over its rows
        return sum(int(row.strip("| ").split(" | ")[column]) for row in table.strip().splitlines()[2:])

    assert counted(out.stdout.split("\n\n")[-1], 2) == total[0]
    alone = subprocess.run([sys.executable, "benchmarks/greedy_split.py", run, "--episodes", "20", "--census-only",
                            "--detail"], cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
    assert alone.returncode == 0, alone.stderr
    head, summary, detail = alone.stdout.split("\n\n")  # the count, the summary, one row per kind of cycle
    assert head.strip().endswith(f"{total[0]} of 20") and counted(summary, 2) == counted(detail, -1) == total[0]
    argv = [sys.executable, "benchmarks/greedy_split.py", run, "--episodes", "20", "--census-only", "--stalls", "2"]
    stalls = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)
    assert stalls.returncode == 0, stalls.stderr
    header = [line for line in stalls.stdout.splitlines() if "stalled greedy episode(s), 6 steps before" in line]
    shown = int(header[0].split()[0])  # as many as asked for, where that many still run 6 steps before the limit
    assert len(header) == 1 and min(2, total[0]) <= shown <= 2
    agents = [line for line in stalls.stdout.splitlines() if line.startswith("agent ")]
    assert len(agents) == 2 * shown  # two agents each
    for line in agents:
        p_bits = [float(x) for x in line.split("p(sent bit = 1) ")[1].split()]
        moves = [float(x) for x in line.split("; moves ")[1].split(";")[0].split()]
        assert len(p_bits) == 4 and all(0 <= p <= 1 for p in p_bits)  # K = 4
        assert len(moves) == 5 and abs(sum(moves) - 1) <= 0.02
    negative = subprocess.run([sys.executable, "benchmarks/greedy_split.py", run, "--stalls", "-1"], cwd=ROOT,
                              capture_output=True, text=True, env=env, timeout=60)  # fmt: skip
    assert negative.returncode == 2 and negative.stderr.strip().splitlines()[-1].endswith("--stalls -1: must be >= 0")
    missing = subprocess.run([sys.executable, "benchmarks/greedy_split.py", str(tmp_path / "nothing")], cwd=ROOT,
                             capture_output=True, text=True, env=env, timeout=60)  # fmt: skip
    assert missing.returncode == 2 and "Traceback" not in missing.stderr and missing.stdout == ""
    assert "no such file or run folder" in missing.stderr.strip().splitlines()[-1]


def _benchmark(name: str) -> Any:
    """A script of benchmarks/ as a module (they are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_shared_words_counts_the_goals_on_one_word_and_the_nearby_pairs_among_them() -> None:
    """A 3x3 grid, 4 bits: the sender's word is the goal's cell index, except that cells 0 and 1 (neighbours) and
    4 and 8 (two cells apart) share a word: 7 words, 4 goals sharing, 1 neighbouring pair, 2 pairs within 3 cells."""
    from types import SimpleNamespace

    import numpy as np

    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.errors import ConfigError

    shared_words = _benchmark("greedy_split").shared_words
    task = TaskConfig(EnvConfig(size=3), ChannelConfig(bits=4))
    word_of = {0: 1, 8: 4}

    def act(planes: np.ndarray, received: np.ndarray, greedy: bool) -> tuple[np.ndarray, np.ndarray]:
        assert greedy and received.shape == (9, task.slots, 4) and not received.any()
        goal = planes[:, 1].reshape(9, 9).argmax(1)
        words = np.array([word_of.get(int(g), int(g)) for g in goal])
        return np.zeros(9, np.int64), ((words[:, None] >> np.arange(4)) & 1).astype(np.uint8)

    controller = SimpleNamespace(task=task, act=act, config={"model": {"message_reads": "observed"}})
    assert shared_words(controller) == (7, 4, 1, 2)
    with pytest.raises(ConfigError, match="--message-reads observed"):
        shared_words(SimpleNamespace(task=task, act=act, config={"model": {"message_reads": "all"}}))


@pytest.mark.parametrize("head", ["bitwise", "onehot"])
def test_hedged_bits_are_the_bits_a_goal_s_word_sends_with_probability_between_the_bounds(head: str) -> None:
    """A 3x3 grid, 2 bits: goal 4's first bit is sent with probability 0.5, goal 7's second with 0.3 and goal 2's
    first with 0.79, goal 8's second with 0.19 (not hedged), every other bit with 0.01 or 0.99. Both heads give each
    bit's marginal."""
    from types import SimpleNamespace

    import torch

    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.policies.heads import make_head

    task = TaskConfig(EnvConfig(size=3), ChannelConfig(bits=2))
    p = torch.full((9, 2), 0.99)
    p[:, 1] = 0.01
    p[4, 0], p[7, 1], p[2, 0], p[8, 1] = 0.5, 0.3, 0.79, 0.19

    def observed_message_logits(planes: torch.Tensor) -> torch.Tensor:
        q = p[planes[:, 1].flatten(1).float().argmax(1)]
        if head == "bitwise":
            return torch.logit(q)
        words = torch.stack(
            [(1 - q[:, 0]) * (1 - q[:, 1]), q[:, 0] * (1 - q[:, 1]), (1 - q[:, 0]) * q[:, 1], q.prod(1)], 1
        )
        return words.log()  # word index i sets bit k where (i >> k) & 1

    policy = SimpleNamespace(observed_message_logits=observed_message_logits, head=make_head(head, 2))
    controller = SimpleNamespace(task=task, policy=policy, config={"model": {"message_reads": "observed"}})
    assert _benchmark("greedy_split").hedged_bits(controller) == (3, 3)


def test_the_cycle_census_names_the_period_of_each_episode_that_never_ends() -> None:
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig

    census = _benchmark("greedy_split").cycle_census
    task = TaskConfig(EnvConfig(size=4, max_steps=24), ChannelConfig(bits=3))

    def constant(move: int, bits: int = 0) -> Any:
        def act(obs: Any) -> tuple[np.ndarray, np.ndarray]:
            B, n = obs.planes.shape[:2]
            return np.full((B, n), move), np.full((B, n, 3), bits, dtype=np.uint8)

        return act

    def to_and_fro(obs: Any) -> tuple[np.ndarray, np.ndarray]:  # down on even steps, up on odd; says its row
        B, n = obs.planes.shape[:2]
        row = obs.planes[:, :, 0].reshape(B, n, -1).argmax(-1) // 4
        bits = np.stack([(row >> k) & 1 for k in range(3)], -1).astype(np.uint8)
        return np.where(obs.t[:, None] % 2 == 0, 2, 1).repeat(n, 1), bits

    # standing still never reaches a goal: every episode is cut, a fixed point with no move and a fixed message
    cut, kinds = census(constant(0, 1), task, 40, 0, 8)
    assert cut == 40 and {k[:3] for k in kinds} == {(1, False, ())} and sum(kinds.values()) == 40
    assert all(lo == hi and (lo > 0) | (lo2 > 0) for *_, ((lo, hi), (lo2, _)) in kinds)  # still, never both home
    # pushing up ends against the top wall: still a period of 1, with both agents choosing a move
    cut, kinds = census(constant(1), task, 40, 0, 8)
    assert cut == sum(kinds.values()) and {k[:3] for k in kinds} == {(1, False, (0, 1))}
    # down then up forever (from the top row) or up and down: period 2, and the messages (each sender's row)
    # change along it; episodes whose goals happen to be met on the way end and are not counted
    cut, kinds = census(to_and_fro, task, 40, 0, 8)
    assert cut == sum(kinds.values()) > 0 and {k[:2] for k in kinds} == {(2, True)}
    assert all(hi == lo + 1 for *_, spans in kinds for lo, hi in spans)  # one step nearer, one step farther
    # a cycle longer than the periods looked for is put down as None
    cut, kinds = census(to_and_fro, task, 40, 0, 1)
    assert {k[:3] for k in kinds} == {(None, False, ())}


def test_update_profile_groups_an_update_s_time_and_ends_with_json() -> None:
    argv = [sys.executable, "benchmarks/update_profile.py", "--num-envs", "4", "--updates", "1"]
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["agent_steps_per_batch"] > 0 and summary["cpu_s_per_update"] > 0
    assert summary["task"] == "10x10, K=7, bitwise"
    assert abs(sum(summary["shares"].values()) - 1.0) < 1e-3 and summary["shares"]["matrix products"] > 0
    assert summary["gflop_per_update"] > 0 and summary["mflop_per_agent_step"] > 0
    parts = summary["parts_ms"]  # a batch by part: play, then the update's critic and policy sides, which sum to it
    assert {"play", "update", "critic: loss and step", "policy: loss and step", "policy: forward"} <= parts.keys()
    assert all(ms >= 0 for ms in parts.values())
    inside = sum(ms for part, ms in parts.items() if part.startswith(("critic", "policy")))
    assert inside == pytest.approx(parts["update"], rel=0.25)  # medians of each part: their sum, near the update's
    bad = subprocess.run([*argv[:2], "--updates", "0"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "updates" in bad.stderr.strip().splitlines()[-1]


def test_update_profile_profiles_another_task_and_head() -> None:
    argv = [sys.executable, "benchmarks/update_profile.py", "--num-envs", "4", "--updates", "1",
            "--size", "5", "--bits", "5"]  # fmt: skip
    out = subprocess.run([*argv, "--messages", "onehot"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1])["task"] == "5x5, K=5, onehot"
    bad = subprocess.run([*argv, "--messages", "morse"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "messages='morse'" in bad.stderr and "Traceback" not in bad.stderr


def test_allocator_times_both_settings_in_turn_and_ends_with_json() -> None:
    argv = [sys.executable, "benchmarks/allocator.py", "--size", "5", "--bits", "4", "--num-envs", "4", "--rounds", "1"]
    out = subprocess.run([*argv, "--updates", "1"], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["task"] == "5x5, K=4, onehot" and summary["update_speedup"] > 0
    assert set(summary["median"]) == {"on", "off"} and all(m["update_s"] > 0 for m in summary["median"].values())
    bad = subprocess.run([*argv, "--updates", "0"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "updates" in bad.stderr.strip().splitlines()[-1] and "Traceback" not in bad.stderr


def test_denormals_times_a_trained_run_s_update_both_ways_and_ends_with_json(tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = str(tmp_path / "run")
    train_tiny_run(run, "--episodes", "32", "--messages", "onehot")
    argv = [sys.executable, "benchmarks/denormals.py", run, "--rounds", "1", "--batches", "1"]
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["task"] == "3x3, K=4, onehot" and summary["update_speedup"] > 0
    assert set(summary["median_update_s"]) == set(summary["agent_steps_per_s"]) == {"on", "off"}
    for bad, named in (([str(tmp_path / "nothing")], "no such file or run folder"), ([run, "--rounds", "0"], "rounds")):
        refused = subprocess.run([sys.executable, "benchmarks/denormals.py", *bad], cwd=ROOT, capture_output=True,
                                 text=True, env=env, timeout=60)  # fmt: skip
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        assert named in refused.stderr.strip().splitlines()[-1]


def test_a_seed_that_diverges_stops_and_is_measured_at_its_last_checkpoint(tmp_path: Path, monkeypatch) -> None:
    """`solve_seed` (and so every ablation row) records a divergence instead of crashing the whole study."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bitcomm.learn.run
    from bitcomm.checkpoint import Diverged
    from solve import solve_seed

    real, calls = bitcomm.learn.run.train, []

    def train_then_diverge(*args, **kwargs):  # the first chunk trains, the second diverges
        calls.append(1)
        if len(calls) > 1:
            raise Diverged("training diverged after 40 episodes: policy.fc1.0.weight holds NaN or inf")
        return real(*args, **kwargs)

    monkeypatch.setattr(bitcomm.learn.run, "train", train_then_diverge)
    args = {"recipe": "reinforced", "estimator": "improved", "messages": "bitwise", "size": 3, "bits": 4,
            "threads": 1, "minutes": 1.0, "chunk": 16, "max_episodes": 64, "eval_episodes": 20,
            "set": [("num_envs", 16), ("anneal_episodes", 64)], "out": str(tmp_path)}  # fmt: skip
    result = solve_seed(args, 0)
    assert len(calls) == 2 and result["episodes"] == 16 and "diverged after 40 episodes" in result["diverged"]
    assert result["final_eval"]["sampled"] > 0  # measured at the checkpoint of the first chunk
    # the rungs' oracle is the one on the episodes that confirm them, not on the training seed's episodes
    task = TaskConfig(EnvConfig(size=3), ChannelConfig(bits=4))
    on_eval_set = evaluate(OraclePolicy(task), task, 20, 12345).mean_episode_length
    config = json.loads((tmp_path / "seed0" / "config.json").read_text())
    assert result["oracle"] == on_eval_set != config["oracle_mean_episode_length"]


def test_greedy_selection_measures_latest_and_best_and_keeps_measured_seeds(tmp_path: Path) -> None:
    argv = [sys.executable, "benchmarks/greedy_selection.py", "--size", "4", "--bits", "4", "--seeds", "2",
            "--episodes", "256", "--held-out-every", "128", "--held-out-episodes", "16", "--eval-episodes", "32",
            "--jobs", "1", "--out", str(tmp_path)]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    summary = json.loads(first.stdout.strip().splitlines()[-1])
    assert [r["seed"] for r in summary["seeds"]] == [0, 1]
    for r in summary["seeds"]:
        best = json.loads((tmp_path / f"seed{r['seed']}" / "checkpoints" / "best.json").read_text())
        assert r["latest"]["episodes"] == 256 and r["best"]["episodes"] == best["episodes"] in (128, 256)
        assert all(r[w]["greedy"] >= 1 and 0 <= r[w]["stalled"] <= 1 for w in ("latest", "best"))
    assert sum(summary["over_seeds"]["best_against_latest"].values()) == 2
    again = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0 and again.stdout.count("(kept)") == 2, again.stderr
    # without a held-out set (the default recipe's runs): the latest checkpoint only, greedy and sampled; `--set`
    # trains with any learning option
    plain = [*argv[:-1], str(tmp_path / "plain"), "--set", "uniform_move=0.02"]
    plain[plain.index("--held-out-every") + 1] = "0"
    out = subprocess.run(plain, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "plain" / "seed0" / "config.json").read_text())["uniform_move"] == 0.02
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(set(r) == {"seed", "run", "latest"} and r["latest"]["sampled"] >= 1 for r in summary["seeds"])
    assert set(summary["over_seeds"]) == {"latest"} and summary["over_seeds"]["latest"]["median_sampled"] >= 1
    bad = subprocess.run([*argv[:2], "--held-out-every", "-1"], cwd=ROOT, capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "held-out-every=-1" in bad.stderr and "Traceback" not in bad.stderr
    bad = subprocess.run([*argv[:2], "--set", "no_such=1"], cwd=ROOT, capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "--set 'no_such=1'" in bad.stderr and "Traceback" not in bad.stderr


def test_training_cut_trains_each_cut_on_the_same_seeds_and_keeps_measured_runs(tmp_path: Path) -> None:
    argv = [sys.executable, "benchmarks/training_cut.py", "--size", "4", "--bits", "4", "--episodes", "128",
            "--cuts", "8,recipe", "--seeds", "1", "--eval-episodes", "16", "--jobs", "1",
            "--out", str(tmp_path)]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    summary = json.loads(first.stdout.strip().splitlines()[-1])
    assert summary["recipe_cut"] == 32 and [row["cut"] for row in summary["cuts"]] == [8, 32]
    for row in summary["cuts"]:
        (run,) = row["runs"]
        config = json.loads((tmp_path / f"cut{row['cut']}" / "seed0" / "config.json").read_text())
        assert config["train_max_steps"] == row["cut"] and config["seed"] == 0 and config["episodes"] == 128
        assert run["latest"]["sampled"] >= 1 and run["latest"]["greedy"] >= 1
    assert "cut 32 (the recipe's)" in first.stdout
    again = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0, again.stderr
    kept = [run for row in json.loads(again.stdout.strip().splitlines()[-1])["cuts"] for run in row["runs"]]
    assert all(run.pop("kept") for run in kept) and kept == [row["runs"][0] for row in summary["cuts"]]
    for cuts, message in (("8,x", "'x' is not a cut"), ("32,recipe", "names the recipe's cut (32) twice")):
        bad = subprocess.run([*argv[:2], "--cuts", cuts], cwd=ROOT, capture_output=True, text=True, env=env)
        assert bad.returncode == 2 and message in bad.stderr and "Traceback" not in bad.stderr


def test_run_marks_reads_loose_runs_as_the_study_tables_do(tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = tmp_path / "run"
    train_tiny_run(run, "--episodes", "64", "--epochs", "1", "--minibatches", "1")
    argv = [sys.executable, "benchmarks/run_marks.py", str(run), str(run), "--marks", "24,1000", "--eval-episodes",
            "50"]  # fmt: skip
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    name = "improved + bitwise, 3x3, 4 bits, env.max_steps=16"  # a task option away from its default is named
    group = json.loads(out.stdout.strip().splitlines()[-1])[name]
    episodes, rolling = np.loadtxt(run / "metrics.csv", delimiter=",", skiprows=1, usecols=(1, 5), unpack=True)
    first = group["per_run"][0]
    assert first["rolling_at"] == {"24": np.interp(24, episodes, rolling), "1000": None}  # not played that far
    below = np.flatnonzero(rolling < 2 * group["oracle"])
    assert (first["reached"]["2x"] or {}).get("episodes") == (int(episodes[below[0]]) if below.size else None)
    assert group["summary"]["rolling_at"]["24"]["n"] == 2 and group["summary"]["rolling_at"]["1000"] is None
    assert "| mean ± 95% over 2 |" in out.stdout
    # what the messages say: marginal minus per-message entropy, over the batches within --window episodes
    with (run / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    near = [float(r["charts/entropy_message_marginal"]) - float(r["charts/entropy_message"])
            for r in rows if abs(float(r["episodes"]) - 24) <= 2000]  # fmt: skip
    assert first["information_at"] == {"24": pytest.approx(sum(near) / len(near)), "1000": None}
    assert "I(observation; message)" in out.stdout
    plain = tmp_path / "plain"  # a recipe without the marginal bonus does not log it: no information
    train_tiny_run(plain, "--episodes", "32", "--epochs", "1", "--minibatches", "1", "--entropy-message-marginal", "0")
    argv = [sys.executable, "benchmarks/run_marks.py", str(plain), "--marks", "16", "--eval-episodes", "50", "--window",
            "0"]  # fmt: skip
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0 and "I(observation" not in out.stdout, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1])[name]["per_run"][0]["information_at"] is None
    bad_flags = (([str(tmp_path / "nothing")], "run="), ([str(run), "--marks", "0"], "--marks"),
                 ([str(run), "--window", "-1"], "window"))  # fmt: skip
    for bad, named in bad_flags:
        refused = subprocess.run([sys.executable, "benchmarks/run_marks.py", *bad], cwd=ROOT, capture_output=True,
                                 text=True, timeout=60)  # fmt: skip
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        assert named in refused.stderr.strip().splitlines()[-1]


def test_speaker_listener_refuses_bad_input_and_never_writes_an_empty_table_into_the_docs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--seeds 0` or a misspelled `--only` trained nothing and then replaced docs/env_learning.md's measured table
    with an empty one, exit 0; a table of one seed gave it a 95% interval of zero width."""
    for bad, named in ((["--seeds", "0"], "seeds=0"), (["--only", "bitcom"], "only='bitcom'")):
        refused = subprocess.run([sys.executable, "benchmarks/speaker_listener.py", *bad, "--out", str(tmp_path)],
                                 cwd=ROOT, capture_output=True, text=True, timeout=60)  # fmt: skip
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        assert named in refused.stderr.strip().splitlines()[-1]
    module = _benchmark("speaker_listener")
    docs = tmp_path / "docs" / "env_learning.md"
    docs.parent.mkdir()
    docs.write_text(f"{module.BEGIN}\nmeasured\n{module.END}\n")
    monkeypatch.setattr(module, "ROOT", tmp_path)
    monkeypatch.setattr(module, "train_one", lambda *args: None)  # a run another call is training: skipped
    monkeypatch.setattr(sys, "argv", ["speaker_listener.py", "--seeds", "1", "--out", str(tmp_path / "runs")])
    with pytest.raises(SystemExit) as stop:
        module.main()
    assert stop.value.code == 2 and "holds no finished run" in capsys.readouterr().err
    assert "measured" in docs.read_text()
    args = module.argparse.Namespace(bits=3, episodes=64, num_envs=8, eval_episodes=10, eval_seed=1000)
    one = {"seed": 0.0, "return": -20.0, "cut": -30.0, "information": 0.5, "wall_s": 3.0}
    line = module.table({"bitcomm": [one]}, args).splitlines()[-1]
    assert "| -20.00 | — (one seed) |" in line and " to " not in line


def test_one_seed_is_no_interval_in_the_demo_tables_and_a_refused_study_is_its_line_alone(tmp_path: Path) -> None:
    """`run_marks.py` printed one run as '41.47 ± 0.00' and `channel_demos.py` as '41.47 (41.47-41.47)', intervals
    of zero width; a study refused by `bitcomm compare` (`--seeds 0`) ended channel_demos in a CalledProcessError
    traceback under the refusal's own line."""
    marks, demos = _benchmark("run_marks"), _benchmark("channel_demos")
    one = {"mean": 41.47, "ci95": [41.47, 41.47], "n": 1}
    assert marks._interval_cell(one, 1) == "41.47" and marks._interval_cell(one, 3) == "41.47 (1 run)"
    two = {"mean": 2.0, "ci95": [1.0, 3.0], "n": 2}
    assert marks._interval_cell(two, 2) == "2.00 ± 1.00" and marks._interval_cell(two, 3) == "2.00 ± 1.00 (2 runs)"
    assert demos._interval([41.47]) == "41.47 (one seed)"
    assert demos._interval([1.0, 3.0]) == "2.00 (-10.71-14.71)"  # t = 12.706 for one degree of freedom
    argv = [sys.executable, "benchmarks/channel_demos.py", "--seeds", "0", "--out", str(tmp_path)]
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines()[-1].endswith("invalid value '0': must be an integer in [1, 1000]")


HELPED = sorted(p.name for p in (ROOT / "benchmarks").glob("*.py") if "ArgumentParser(" in p.read_text())


@pytest.mark.parametrize("script", HELPED)
def test_a_benchmark_s_help_says_what_it_measures_in_whole_sentences(script: str) -> None:
    """`--help` (the README says to read it) opens with the docstring's first paragraph, not its first line,
    which a wrapped docstring cuts mid-sentence ("... and does keeping the checkpoint")."""
    out = subprocess.run(
        [sys.executable, f"benchmarks/{script}", "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    description = out.stdout.split("\n\n")[1]  # after the usage lines
    assert description.rstrip().endswith((".", "?", ")")), description
