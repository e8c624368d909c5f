"""`bitcomm baseline` run as a user runs it: in a subprocess, reading its JSON and its exit status."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

KEYS = {"mean_episode_length", "ci95", "mean_team_return", "success_rate", "episodes"}


def bitcomm_command() -> list[str]:
    """The installed `bitcomm` script beside this interpreter, else the module."""
    script = Path(sys.executable).with_name("bitcomm")
    if script.exists():
        return [str(script)]
    found = shutil.which("bitcomm")
    return [found] if found else [sys.executable, "-m", "bitcomm.cli"]


def baseline(*flags: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*bitcomm_command(), "baseline", *flags], capture_output=True, text=True, timeout=120, check=False
    )


def baseline_json(*flags: str) -> dict:
    proc = baseline(*flags, "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert KEYS <= set(out)
    return out


@pytest.fixture(scope="module")
def oracle_reference() -> dict:
    return baseline_json("--policy", "oracle", "--episodes", "20000", "--seed", "1")


def test_oracle_measures_the_reference_level(oracle_reference: dict) -> None:
    """SPEC section 6: 8.79 steps and -1.30 team return, computed by enumeration."""
    out = oracle_reference
    assert out["episodes"] == 20000
    assert abs(out["mean_episode_length"] - 8.79) < 0.1
    assert abs(out["mean_team_return"] - (-1.30)) < 0.05
    assert out["success_rate"] == 1.0
    lo, hi = out["ci95"]
    assert lo < out["mean_episode_length"] < hi and hi - lo < 0.2


def test_random_policy_mostly_runs_to_truncation() -> None:
    out = baseline_json("--policy", "random", "--episodes", "300", "--seed", "1")
    assert 245 < out["mean_episode_length"] < 256
    assert out["success_rate"] < 0.1


def test_the_random_policy_s_interval_never_passes_the_episode_cap() -> None:
    """Over 3 episodes of which one ends early (21.33 steps on average), t standard errors reach past both 1 step
    and the 30-step cap; the interval stays within what an episode can last, and one episode's is all that is
    possible."""
    out = baseline_json("--policy", "random", "--episodes", "3", "--seed", "2", "--size", "3", "--max-steps", "30")
    assert 0 < out["success_rate"] < 1 and out["ci95"] == [1.0, 30.0]
    one = baseline_json("--policy", "random", "--episodes", "1", "--seed", "1", "--max-steps", "40")
    assert one["ci95"] == [1.0, 40.0]


def test_bit_flips_make_the_oracle_measurably_worse(oracle_reference: dict) -> None:
    noisy = baseline_json("--policy", "oracle", "--episodes", "20000", "--seed", "1", "--flip-prob", "0.05")
    assert noisy["ci95"][0] > oracle_reference["ci95"][1]  # the intervals do not overlap
    assert noisy["mean_team_return"] < oracle_reference["mean_team_return"]


def test_human_readable_output() -> None:
    proc = baseline("--policy", "oracle", "--episodes", "50", "--seed", "0")
    assert proc.returncode == 0, proc.stderr
    assert "mean episode length" in proc.stdout


@pytest.mark.parametrize(
    ("flags", "parameter", "value"),
    [
        (["--size", "1"], "size", "1"),
        (["--agents", "1"], r"--agents\b", "1"),  # the flag, not the field n_agents
        (["--flip-prob", "1.5"], "flip.prob", "1.5"),
        (["--flip-prob", "-0.1"], "flip.prob", "-0.1"),
        (["--drop-prob", "2"], "drop.prob", "2"),
        (["--drop-prob", "-1"], "drop.prob", "-1"),
        (["--delay", "0"], "delay", "0"),
        (["--observes", "0,1"], "observes", r"\(0, 1\)"),
        # nobody sees agent 2's goal: the map is at fault, not the recipients (no recipients could fix it)
        (["--size", "3", "--bits", "4", "--agents", "3", "--observes", "1,0,0"], "observes", r"\(1, 0, 0\).*agent 2"),
        (["--bits", "6"], "bits", "6"),
        (["--size", "ten"], "size", "ten"),
        (["--size", "2.5"], "size", "2.5"),
        (["--episodes", "0"], "episodes", "0"),
        (["--max-steps", "0"], "max.steps", "0"),
    ],
)
def test_bad_value_is_one_line_and_exit_status_2(flags: list[str], parameter: str, value: str) -> None:
    proc = baseline("--policy", "oracle", "--episodes", "10", *flags)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr  # no traceback, no usage dump
    assert "Traceback" not in proc.stderr
    assert re.search(parameter, lines[0]) and re.search(value, lines[0]), lines[0]
    assert proc.stdout == ""


def test_a_reader_that_stops_early_ends_the_command_quietly() -> None:
    """`bitcomm ... --json | head`: the reader has what it wanted. It was 'error: Broken pipe' and exit status 1; now
    nothing on stderr and 141, what a shell reports for `cat` in the same place."""
    proc = subprocess.Popen(
        [*bitcomm_command(), "baseline", "--episodes", "50", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # before the command writes: its write meets a closed pipe
    assert proc.wait(timeout=120) == 141
    assert proc.stderr.read() == ""
