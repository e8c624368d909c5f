"""Does the training cut matter on a large grid? The figures behind the recipe's cut rule (docs/tuning.md, session 53).

Trains the same seeds of a recipe (improved + bitwise under the default unless told otherwise) once for each cut in
`--cuts` (training episodes cut at that many steps; `recipe` is the cut the recipe itself chooses for the grid), as
`bitcomm train --size N --episodes E --seed S --threads 1 [--train-max-steps C]` trains them, then plays each run's
latest checkpoint sampled and greedily on `--eval-episodes` episodes of `--eval-seed`, as `bitcomm eval RUN
--episodes M --seed V [--greedy]` plays them, and prints one row per cut: the mean episode length, sampled / greedy,
with the share of episodes that reached the goal, seed by seed, and the oracle's on the same episodes. A run already
measured in `--out` is kept and an unfinished one resumes, so a study stopped part way goes on where it stopped. The
last line printed is one JSON object.

    python benchmarks/training_cut.py --size 32 --bits 10 --episodes 200000 --cuts 32,64,recipe --seeds 1 \\
        --eval-episodes 1000 --eval-seed 1000 --out runs/training-cut-32        # 96 steps is the recipe's at 32x32
    python benchmarks/training_cut.py --size 24 --bits 10 --episodes 160000 --cuts 32,recipe --seeds 2 \\
        --eval-episodes 1000 --eval-seed 1000 --out runs/training-cut-24
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from greedy_selection import _config, measure_seed  # benchmarks/ is not a package: the script's folder is on the path
from solve import add_seed_flags, check_seed_flags, seed_range

RECIPE_CUT = "recipe"


def parse_cuts(text: str) -> list[int | None]:
    """`32,64,recipe` -> [32, 64, None]; None is the recipe's own cut."""
    from bitcomm.errors import ConfigError

    cuts: list[int | None] = []
    for item in text.split(","):
        item = item.strip()
        if item == RECIPE_CUT:
            cut = None
        elif item.isascii() and item.isdigit():
            cut = int(item)
        else:
            raise ConfigError(f"--cuts: {item!r} is not a cut; give whole numbers of steps (0: whole episodes) or "
                              f"{RECIPE_CUT!r}")  # fmt: skip
        if cut in cuts:
            raise ConfigError(f"--cuts: {item!r} is given twice")
        cuts.append(cut)
    return cuts


def _measure(item: tuple[dict[str, Any], int]) -> dict[str, Any]:
    return measure_seed(*item)


def main() -> None:
    from bitcomm.errors import ConfigError, check_int
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.reference import OraclePolicy

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_seed_flags(ap, run="run")
    ap.add_argument("--episodes", type=int, default=200_000, help="training budget per run")
    ap.add_argument("--cuts", default=f"32,{RECIPE_CUT}", help=f"comma-separated steps, or {RECIPE_CUT!r}")
    ap.add_argument("--eval-episodes", type=int, default=1000)
    ap.add_argument("--eval-seed", type=int, default=1000, help="the episodes the 32x32 study evaluates on")
    ap.add_argument("--out", type=Path, default=Path("runs/training-cut"))
    a = ap.parse_args()
    try:  # bad input is one line before any run starts
        check_seed_flags(a, "eval_episodes", "episodes")
        check_int("eval_seed", a.eval_seed, 0)
        cuts = parse_cuts(a.cuts)
        base = {k: v for k, v in vars(a).items() if k != "cuts"}
        base.update(out=str(a.out), held_out_every=0, held_out_episodes=1000)  # no held-out set
        recipes = _config({**base, "train_max_steps": None}, a.first_seed)  # the recipe's own cut, on the task
        recipe_cut, task = recipes.train_max_steps, recipes.task
        steps = [recipe_cut if cut is None else _config({**base, "train_max_steps": cut}, 0).train_max_steps
                 for cut in cuts]  # fmt: skip
        if len(set(steps)) < len(steps):
            raise ConfigError(f"--cuts: {a.cuts!r} names the recipe's cut ({recipe_cut}) twice")
        oracle = evaluate(OraclePolicy(task), task, a.eval_episodes, a.eval_seed)
    except ConfigError as err:
        ap.error(str(err))
    seeds = seed_range(a)
    print(
        f"training cut: {a.recipe}, {a.estimator} + {a.messages}, {a.size}x{a.size}, {a.bits} bits, "
        f"{a.episodes} episodes, cuts {steps} (the recipe's: {recipe_cut}), seeds {list(seeds)}; oracle "
        f"{oracle.mean_episode_length:.2f} on {a.eval_episodes} episodes of seed {a.eval_seed}; out {a.out}",
        flush=True,
    )
    jobs = [
        ({**base, "train_max_steps": cut, "out": str(a.out / f"cut{cut}")}, seed) for cut in steps for seed in seeds
    ]
    with ProcessPoolExecutor(min(a.jobs, len(jobs)), mp_context=mp.get_context("spawn")) as pool:
        results = list(pool.map(_measure, jobs))
    rows = []
    for i, cut in enumerate(steps):
        runs = results[i * len(seeds) : (i + 1) * len(seeds)]
        cells = [
            f"seed {r['seed']}: {r['latest']['sampled']:.2f} ({1 - r['latest']['sampled_stalled']:.3f}) / "
            f"{r['latest']['greedy']:.2f} ({1 - r['latest']['stalled']:.3f})"
            for r in runs
        ]
        label = f"{cut}" + (" (the recipe's)" if cut == recipe_cut else "")
        print(f"cut {label}: sampled / greedy (success)  " + "  ".join(cells), flush=True)
        rows.append({"cut": cut, "runs": runs})
    print(json.dumps({**base, "recipe_cut": recipe_cut, "oracle": oracle.mean_episode_length, "cuts": rows}))


if __name__ == "__main__":
    main()
