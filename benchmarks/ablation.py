"""Single-change ablations between two recipes (issue 16): what each of the default recipe's choices is worth.

With `--base paper --target reinforced` (the default), each option on which the two recipes differ is set in turn
to the target's value, one change per row, everything else the paper's; with `--base reinforced --target paper`,
each is set back in turn. Options that only mean something together change as one row (`GROUPS`: PPO-style reuse
is epochs, minibatches and clip at once). The first row is the base itself, the last the target itself.

Every row trains improved + bitwise with `benchmarks/solve.py`'s `solve_seed` for `--minutes` of training per seed
(evaluation excluded) and reports the episodes and seconds until sampled play is below 2x and 1.15x the oracle
(confirmed on 2,000 fixed episodes) and the final sampled and greedy episode length (a row whose training diverges
is measured at its last checkpoint and marked "then diverged"). Rows run one after another,
each with the whole machine (`--threads` torch threads for synchronous rows; an asynchronous row runs its
`workers` processes), so their seconds compare. Each row's result is kept in `<out>/<row>/result.json`: a
stopped ablation rerun with the same flags skips finished rows.

A row whose options decay the learning rates (`anneal_lr`) needs `--max-episodes N`: its schedule's horizon and
its episode budget (a row that does not anneal trains for `--minutes` only, as before).

Rows stopped by the clock play different numbers of episodes (a slow row, or a slow moment of a shared machine,
plays fewer), so `--marks 20000,40000,60000` adds a column that reads every row's rolling training length at those
episodes (interpolated between logged batches, as `bitcomm compare` reads its curves; "—" past a row's last):
the rows at equal episodes, where their schedules stand at the same point.

    python benchmarks/ablation.py --size 4 --bits 4 --minutes 1 --max-episodes 30000   # from paper, each fix on
    python benchmarks/ablation.py --base reinforced --target paper --size 4 --bits 4 --minutes 1 --max-episodes 30000
    python benchmarks/ablation.py --base reinforced --target paper --size 10 --bits 7 --minutes 5 \
        --max-episodes 75000 --chunk 4096 --threads 1 --marks 20000,40000,60000     # the paper's task (results 4d)
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig  # noqa: E402
from bitcomm.learn.config import recipe_values  # noqa: E402
from bitcomm.learn.recipes import NO_SPARE_WORDS  # noqa: E402
from bitcomm.studies.compare import read_curve  # noqa: E402
from run_marks import parse_marks, reached_cell, rolling_at_marks  # noqa: E402  (benchmarks/ is not a package)
from solve import solve_seed  # noqa: E402

GROUPS: dict[str, tuple[str, ...]] = {"ppo_reuse": ("epochs", "minibatches", "clip")}
"""Options changed together: a clip range means nothing without reuse, and reuse is the epochs x minibatches."""


OBSERVED_ONLY = tuple(NO_SPARE_WORDS)
"""Options that need a message head reading only the observed goal (`message_reads` `observed`): those a recipe
gives way with where its head reads more (`recipes.NO_SPARE_WORDS`)."""


def _fit(change: dict[str, Any], base: dict[str, Any]) -> dict[str, Any]:
    """The couplings between the recipes' options. A batch of E episodes splits into at most E minibatches: where
    a row leaves fewer episodes per batch than minibatches, the minibatches follow. A row that turns on an option
    of `OBSERVED_ONLY` over a head that reads everything brings the observed head with it."""
    episodes = change.get("num_envs", base.get("num_envs", 1))
    if change.get("minibatches", base.get("minibatches", 1)) > episodes:
        change = {**change, "minibatches": episodes}
    if (
        any(change.get(k, 0) for k in OBSERVED_ONLY)
        and change.get("message_reads", base["message_reads"]) != "observed"
    ):
        change = {**change, "message_reads": "observed"}
    return change


def rows(base: str, target: str, task: TaskConfig) -> list[tuple[str, dict[str, Any]]]:
    """(name, overrides on the base recipe): the base, one row per option or group in which the two recipes differ
    on `task`, the target."""
    b, t = recipe_values(base, task), recipe_values(target, task)
    differing = [k for k in t if b.get(k) != t[k]]
    grouped = {k for keys in GROUPS.values() for k in keys}
    out: list[tuple[str, dict[str, Any]]] = [(base, {})]
    for name, keys in GROUPS.items():
        if any(k in differing for k in keys):
            out.append((name, _fit({k: t[k] for k in keys}, b)))
    out += [(k, _fit({k: t[k]}, b)) for k in differing if k not in grouped]
    out.append((target, {k: t[k] for k in differing}))
    return out


def rolling_cell(run: Path, marks: tuple[int, ...]) -> str:
    """The run's rolling training length at each of `marks` episodes, "—" past its last logged batch."""
    if not (run / "metrics.csv").is_file():
        return " / ".join("—" for _ in marks)
    at = rolling_at_marks(read_curve(run), marks)
    return " / ".join("—" if at[m] is None else f"{at[m]:.2f}" for m in marks)


def table(results: list[tuple[str, dict[str, Any], dict[str, Any]]], a: argparse.Namespace) -> str:
    marks = f" | rolling at {' / '.join(f'{m:,}' for m in a.marks)} episodes" if a.marks else ""
    lines = [
        f"{a.size}x{a.size} grid, K = {a.bits}, improved + bitwise, seed {a.seed}, {a.minutes:g} min of training per "
        f"row; from `{a.base}`, one change toward `{a.target}` per row (oracle "
        f"{results[0][2]['oracle']:.2f} on the evaluation episodes).",
        "",
        f"| row | change | 2x oracle | 1.15x oracle | final sampled | final greedy | episodes played{marks} |",
        "| --- | --- | --- | --- | --- | --- | ---" + (" | ---" if a.marks else "") + " |",
    ]
    for name, change, r in results:
        shown = ", ".join(f"{k}={v}" for k, v in change.items()) if name not in (a.base, a.target) else "—"
        lines.append(
            f"| {name} | {shown} | {reached_cell(r['reached']['2x'])} | {reached_cell(r['reached']['1.15x'])} | "
            f"{r['final_eval']['sampled']:.2f} | {r['final_eval']['greedy']:.2f} | {r['episodes']:,}"
            f"{' (then diverged)' if r.get('diverged') else ''}"
            + (f" | {rolling_cell(a.out / name / f'seed{a.seed}', a.marks)}" if a.marks else "")
            + " |"
        )
    return "\n".join(lines)


def main() -> None:
    from bitcomm.learn.recipes import RECIPES

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", choices=tuple(RECIPES), default="paper")
    ap.add_argument("--target", choices=tuple(RECIPES), default="reinforced")
    ap.add_argument("--size", type=int, default=4)
    ap.add_argument("--bits", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--minutes", type=float, default=1.5, help="training wall time per row")
    ap.add_argument("--chunk", type=int, default=512, help="episodes between checks")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of a synchronous row")
    ap.add_argument("--only", default="", help="comma-separated row names (default: all)")
    ap.add_argument(
        "--max-episodes", type=int, default=None, help="horizon and episode budget of a row that anneals its rates"
    )
    ap.add_argument("--out", type=Path, default=None, help="default runs/ablation/<base>-to-<target>-<size>x<size>")
    marks_help = "comma-separated episodes at which to read every row's rolling length"
    ap.add_argument("--marks", type=parse_marks, default=(), help=marks_help)
    a = ap.parse_args()
    if a.base == a.target:
        ap.error(f"--target {a.target!r}: must differ from --base")
    if a.minutes <= 0 or a.chunk < 1 or a.threads < 1 or a.size < 2 or a.bits < 1:
        ap.error("--minutes must be > 0; --chunk, --threads, --bits >= 1; --size >= 2")
    if a.max_episodes is not None and a.max_episodes < 1:
        ap.error(f"--max-episodes {a.max_episodes}: must be >= 1")
    out = a.out = a.out or Path("runs/ablation") / f"{a.base}-to-{a.target}-{a.size}x{a.size}"
    plan = rows(a.base, a.target, TaskConfig(EnvConfig(size=a.size), ChannelConfig(bits=a.bits)))
    if a.only:
        names = {n for n, _ in plan}
        wanted = [n.strip() for n in a.only.split(",")]
        unknown = [n for n in wanted if n not in names]
        if unknown:
            ap.error(f"--only {unknown[0]!r}: not a row; rows are {', '.join(names)}")
        plan = [(n, c) for n, c in plan if n in wanted]
    annealing = [n for n, c in plan if {**RECIPES[a.base], **c}.get("anneal_lr")]
    if annealing and a.max_episodes is None:
        ap.error(f"rows {', '.join(annealing)} decay their rates over a budget: give --max-episodes N (their horizon)")
    results = []
    for name, change in plan:
        folder = out / name
        saved = folder / "result.json"
        settings = {"recipe": a.base, "set": change, "size": a.size, "bits": a.bits, "seed": a.seed,
                    "minutes": a.minutes, "chunk": a.chunk, "threads": a.threads}  # fmt: skip
        options = list(change.items())
        if name in annealing:  # one schedule over the row's chunks, ending at its episode budget
            settings["max_episodes"] = a.max_episodes
            options.append(("anneal_episodes", a.max_episodes))
        if saved.is_file() and json.loads(saved.read_text())["settings"] == json.loads(json.dumps(settings)):
            result = json.loads(saved.read_text())["result"]
        else:
            args = {**settings, "estimator": "improved", "messages": "bitwise", "eval_episodes": 2000, "set": options,
                    "max_episodes": settings.get("max_episodes", 10**9), "out": str(folder)}  # fmt: skip
            shutil.rmtree(folder / f"seed{a.seed}", ignore_errors=True)  # a row left unfinished or by other flags
            result = solve_seed(args, a.seed)
            folder.mkdir(parents=True, exist_ok=True)
            saved.write_text(json.dumps({"settings": settings, "result": result}, indent=1) + "\n")
        results.append((name, change, result))
        r = result
        print(f"{name}: 2x {reached_cell(r['reached']['2x'])}, 1.15x {reached_cell(r['reached']['1.15x'])}, "
              f"final sampled {r['final_eval']['sampled']:.2f} / greedy {r['final_eval']['greedy']:.2f}",
              flush=True)  # fmt: skip
    text = table(results, a)
    (out / "table.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
