"""The README quotes `benchmarks/train_speed.py`: it must run as written and print what the README reads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

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
