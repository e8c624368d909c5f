"""MPE2 `simple_speaker_listener_v4` with the speaker talking through bitcomm's channel (issue 18, item 4).

The speaker sees the goal landmark's colour; the listener sees the landmarks and must reach the goal.
Configurations, each trained on `--seeds` seeds with `bitcomm train --env` (pure reinforcement, SPEC 7):

- `bitcomm`:  improved + bitwise, K bits through bitcomm's channel; the speaker's native communication action
  fixed to 0 (`--fixed-actions '{"speaker_0": 0}'`), so bitcomm's channel is the only way to talk;
- `dropped`:  the same with every message dropped (`--drop-prob 1`): the learned no-communication level;
- `native`:   the env's own Discrete communication action live (the speaker's action head learns it) and
  bitcomm's channel cut (`--drop-prob 1`): the same learner talking through MPE2's channel;
- with `--techniques`: standard/improved x bitwise/onehot through bitcomm's channel (`bitcomm` is improved +
  bitwise).

Only the speaker talks through bitcomm's channel (topology speaker_0 -> listener_0), as in the env itself.

Each run is measured on the same `--eval-episodes` episodes (seed `--eval-seed`, sampling); `bitcomm` runs
are also measured with the channel cut at evaluation (`cut at eval`). The table gives the mean team return
(the sum over the episode's 25 steps of the shared reward, minus the squared distance to the goal) over seeds
with a 95% Student's t interval (`bitcomm.stats`) and the information the speaker's messages carry
about the goal colour (estimated from counts over 256 episodes), and writes it into docs/env_learning.md between
markers. Finished runs are skipped and unfinished ones resumed, so the script can be stopped and rerun; a run
another call of the script is training (its folder's lock is held) is skipped, so two calls share the work.

    python benchmarks/speaker_listener.py [--episodes 8960] [--seeds 3] [--jobs 1] [--threads 1] [--techniques]
        [--out runs/speaker_listener] [--bits 3] [--eval-episodes 1000] [--only NAME,...] [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENV = "mpe2.simple_speaker_listener_v4:parallel_env"
FIXED = ["--fixed-actions", '{"speaker_0": 0}']
TOPOLOGY = ["--topology", '[["speaker_0", "listener_0"]]']
"""Only the speaker talks, as in the env itself: a listener's messages would only be noise in the speaker's input."""
CUT = ["--drop-prob", "1"]
LEARNING = ["--max-grad-norm", "10", "--critic-lr", "3e-3", "--entropy-message", "0.003", "--obs-norm"]
"""Tuned on seed 0 with runs of 3,200-5,760 episodes (docs/env_learning.md): the critic's squared errors start in
the hundreds, and with the default clip at norm 1 and rate 1e-3 it learned slowly; this reached -16.7 on 500
evaluation episodes where the defaults and four other variants reached -17.2 to -22.8. With `--obs-norm` the
speaker's messages carried 0.75 bits about the goal after 5,120 episodes, against 0.02-0.04 without."""
CONFIGS: dict[str, list[str]] = {
    "bitcomm": [*FIXED, "--estimator", "improved", "--messages", "bitwise"],
    "dropped": [*FIXED, *CUT, "--estimator", "improved", "--messages", "bitwise"],
    "native": [*CUT, "--estimator", "improved", "--messages", "bitwise"],
}
TECHNIQUES: dict[str, list[str]] = {
    f"{est}-{msg}": [*FIXED, "--estimator", est, "--messages", msg]
    for est in ("standard", "improved")
    for msg in ("bitwise", "onehot")
    if (est, msg) != ("improved", "bitwise")
}
LABELS = {
    "bitcomm": "improved + bitwise through bitcomm's channel (speaker's native action fixed)",
    "dropped": "the same, every message dropped (trained with --drop-prob 1)",
    "native": "the env's native Discrete communication, bitcomm's channel cut",
    "standard-bitwise": "standard + bitwise through bitcomm's channel",
    "standard-onehot": "standard + one-hot through bitcomm's channel",
    "improved-onehot": "improved + one-hot through bitcomm's channel",
}
MAX_SEEDS = 100
BEGIN, END = "<!-- speaker_listener:begin -->", "<!-- speaker_listener:end -->"


def finished_episodes(run: Path) -> int:
    latest = run / "checkpoints" / "latest.json"
    return int(json.loads(latest.read_text())["episodes"]) if latest.is_file() else 0


def train_one(name: str, seed: int, args: argparse.Namespace) -> Path:
    """Train (or resume, or skip) one run; returns its folder."""
    run = args.out / f"{name}-s{seed}"
    done = finished_episodes(run)
    if done >= args.episodes:
        return run
    argv = [sys.executable, "-m", "bitcomm.cli", "train", "--out", str(run), "--episodes", str(args.episodes)]
    argv += ["--threads", str(args.threads), "--quiet", "--eval-episodes", "0"]
    if done > 0:
        argv += ["--resume"]
    else:
        argv += ["--env", ENV, "--bits", str(args.bits), "--seed", str(seed), "--num-envs", str(args.num_envs)]
        argv += [*(CONFIGS | TECHNIQUES)[name], *TOPOLOGY, *LEARNING]
    t0 = time.time()
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    out = subprocess.run(argv, capture_output=True, text=True, env=env)
    if out.returncode != 0 and "is writing this run folder" in out.stderr:
        print(f"skipped {run.name}: another process is training it", flush=True)
        return run
    if out.returncode != 0:
        raise SystemExit(f"{name} seed {seed} failed: {out.stderr.strip()}")
    print(f"trained {run.name} in {time.time() - t0:.0f} s", flush=True)
    return run


def evaluate_one(run: Path, args: argparse.Namespace, cut: bool) -> float:
    """Mean team return of a run on the evaluation episodes (cached in the run folder)."""
    import torch

    from bitcomm.learn.env_eval import evaluate_env

    torch.set_num_threads(args.threads)
    cache = run / f"eval{'-cut' if cut else ''}-{args.eval_seed}-{args.eval_episodes}.json"
    if cache.is_file() and json.loads(cache.read_text())["episodes_trained"] == finished_episodes(run):
        return float(json.loads(cache.read_text())["mean_team_return"])
    result = evaluate_env(run, args.eval_episodes, args.eval_seed, drop_prob=1.0 if cut else None)
    cache.write_text(json.dumps({**result.to_dict(), "episodes_trained": finished_episodes(run)}) + "\n")
    return result.mean_team_return


def message_information(run: Path, native: bool, args: argparse.Namespace) -> float:
    """I(goal colour; what the speaker sends), in bits, estimated by counts over 256 seeded episodes: its bitcomm
    message, or (`native`) its own communication action. The goal is the speaker's observation (one colour)."""
    import torch

    from bitcomm.channel.core import bits_to_index
    from bitcomm.learn.env_eval import load_env_policy
    from bitcomm.learn.env_rollout import make_vec, play

    cache = run / f"information-{args.eval_seed}.json"
    if cache.is_file() and json.loads(cache.read_text())["episodes_trained"] == finished_episodes(run):
        return float(json.loads(cache.read_text())["bits"])
    cfg, policy = load_env_policy(run)
    ro = play(make_vec(cfg, 256), policy, np.random.SeedSequence(args.eval_seed), torch.Generator().manual_seed(0))
    goal = ro.obs[:, :, 0, :3].argmax(-1).flatten().numpy()
    said = (ro.actions[:, :, 0] if native else bits_to_index(ro.bits[:, :, 0])).flatten().numpy()
    joint = np.zeros((3, int(said.max()) + 1))
    np.add.at(joint, (goal, said), 1)
    p = joint / joint.sum()
    outer = p.sum(1, keepdims=True) * p.sum(0, keepdims=True)
    bits = float(np.sum(p[p > 0] * np.log2(p[p > 0] / outer[p > 0])))
    cache.write_text(json.dumps({"bits": bits, "episodes_trained": finished_episodes(run)}) + "\n")
    return bits


def wall_seconds(run: Path) -> float:
    import csv

    with (run / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return float(rows[-1]["wall_s"]) if rows else float("nan")


def table(results: dict[str, list[dict[str, float]]], args: argparse.Namespace) -> str:
    from bitcomm.stats import mean_interval

    lines = [
        f"MPE2 `simple_speaker_listener_v4`, K = {args.bits} bits, delay 1, {args.episodes} training episodes per run "
        f"({args.num_envs} per batch; `{' '.join(LEARNING)}`), evaluation on {args.eval_episodes} episodes "
        f"(seed {args.eval_seed}, sampling). "
        "Mean team return (higher is better) over seeds, 95% Student's t interval; `cut at eval`: the same "
        "policies with every message dropped at evaluation; `I(goal; message)`: bits the speaker's messages (or, "
        "native, its communication action) carry about the goal colour (at most log2 3 = 1.58).",
        "",
        "| configuration | seeds | mean team return | 95% interval | cut at eval | I(goal; message) | training s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, rows in results.items():
        if not rows:
            continue
        mean, lo, hi = mean_interval([r["return"] for r in rows])
        spread = f"{lo:.2f} to {hi:.2f}" if len(rows) > 1 else "— (one seed)"
        cuts = [r["cut"] for r in rows if "cut" in r]
        cut = f"{np.mean(cuts):.2f}" if cuts else ""
        seeds = ",".join(str(int(r["seed"])) for r in rows)
        info, wall = np.mean([r["information"] for r in rows]), np.mean([r["wall_s"] for r in rows])
        lines.append(f"| {LABELS[name]} | {seeds} | {mean:.2f} | {spread} | {cut} | {info:.2f} | {wall:.0f} |")
    return "\n".join(lines)


def write_docs(text: str, command: str) -> None:
    doc = ROOT / "docs" / "env_learning.md"
    body = doc.read_text()
    if BEGIN not in body or END not in body:
        raise SystemExit(f"{doc} lacks the markers {BEGIN} / {END}")
    head, rest = body.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    doc.write_text(f"{head}{BEGIN}\n{text}\n\nProduced by `{command}`.\n{END}{tail}")


def check_args(p: argparse.ArgumentParser, args: argparse.Namespace, names: list[str]) -> None:
    """Bad input is one line (exit 2) before anything trains, and before the docs' table is rewritten."""
    from bitcomm.errors import ConfigError, bad_value, check_int

    try:
        for name in ("episodes", "num_envs", "seeds", "bits", "jobs", "threads", "eval_episodes"):
            check_int(name, getattr(args, name), 1)
        check_int("eval_seed", args.eval_seed, 0)
        if args.seeds > MAX_SEEDS:
            raise bad_value("seeds", args.seeds, f"must be at most {MAX_SEEDS}")
        unknown = [n for n in args.only.split(",") if n and n not in names]
        if unknown:
            with_techniques = "" if args.techniques else " (with --techniques also " + ", ".join(TECHNIQUES) + ")"
            raise bad_value("only", args.only, f"a comma-separated subset of {', '.join(names)}{with_techniques}")
    except ConfigError as err:
        p.error(str(err))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=8960, help="training episodes per run (about 3 min at 1 thread)")
    p.add_argument("--num-envs", type=int, default=64, help="episodes per batch")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--bits", type=int, default=3)
    p.add_argument("--jobs", type=int, default=1, help="runs at once")
    p.add_argument("--threads", type=int, default=1, help="torch threads per run")
    p.add_argument("--techniques", action="store_true", help="also the other three of the four techniques")
    p.add_argument("--only", default="", help="comma-separated configuration names (default: all)")
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--eval-seed", type=int, default=1000)
    p.add_argument("--out", type=Path, default=Path("runs/speaker_listener"))
    p.add_argument("--no-docs", action="store_true", help="print the table only")
    args = p.parse_args()
    names = list(CONFIGS) + (list(TECHNIQUES) if args.techniques else [])
    check_args(p, args, names)
    if args.only:
        names = [n for n in args.only.split(",") if n in names]
    jobs = [(name, seed) for seed in range(args.seeds) for name in names]
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        list(pool.map(lambda job: train_one(*job, args), jobs))
    # the table holds every finished run in --out, so runs of an earlier call (other --only) stay in it
    results: dict[str, list[dict[str, float]]] = {name: [] for name in [*CONFIGS, *TECHNIQUES]}
    for name in results:
        for seed in range(MAX_SEEDS):
            run = args.out / f"{name}-s{seed}"
            if finished_episodes(run) < args.episodes:
                continue
            row = {"seed": seed, "return": evaluate_one(run, args, cut=False), "wall_s": wall_seconds(run)}
            row["information"] = message_information(run, name == "native", args)
            if name == "bitcomm":
                row["cut"] = evaluate_one(run, args, cut=True)
            results[name].append(row)
    text = table(results, args)
    print(text)
    if not any(results.values()) and not args.no_docs:  # an empty table must not replace the measured one
        p.error(f"invalid out={str(args.out)!r}: holds no finished run of {args.episodes} episodes; the docs are "
                "left as they are")  # fmt: skip
    if not args.no_docs:
        write_docs(text, "python " + " ".join(["benchmarks/speaker_listener.py", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
