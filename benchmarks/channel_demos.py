"""Issue 18's goal-exchange demonstrations: n agents on a ring, and learning under bit flips.

1. Agents: `bitcomm compare` (the four techniques and the no-communication baseline) with 3 and 4
   agents on a ring (each sees the next one's goal and is the only one told it), S seeds, on a small
   grid so that the study fits a laptop; the table holds each setting's own oracle.
2. Flips: improved + bitwise (and the no-communication baseline) at flip probabilities p, S seeds;
   every run is then read with `bitcomm analyze`: the information its received messages carry
   about the goal (I(goal; received), bits, plug-in estimate on 200,000 deliveries) beside the
   channel's capacity K (1 - H(p)), and its episode length.

Every study resumes (finished runs are kept), so an interrupted script picks up where it stopped.
Prints Markdown tables and writes them, with the commands, to `--out`/demos.md.

    python benchmarks/channel_demos.py --seeds 3 --jobs 1 --threads 1            # both parts
    python benchmarks/channel_demos.py --part flips --flips 0,0.05,0.1,0.2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from bitcomm.stats import mean_interval


def bitcomm(*args: str, threads: int) -> str:
    """Run one `bitcomm` command in a child process (so torch's thread count is its own); its stdout."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    cmd = [sys.executable, "-c", "import sys; from bitcomm.cli import main; sys.exit(main())", *args]
    print("$ bitcomm " + " ".join(args), flush=True)
    out = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True)
    if out.returncode != 0:  # its one line (a bad --seeds, --flips ...) is on stderr already: no traceback here
        raise SystemExit(out.returncode)
    return out.stdout


def _interval(values: list[float]) -> str:
    """Mean and 95% interval over seeds (Student's t): '44.27 (42.20-46.34)'; one seed has no interval."""
    mean, lo, hi = (float(x) for x in mean_interval(values))
    return f"{mean:.2f} ({lo:.2f}-{hi:.2f})" if len(values) > 1 else f"{mean:.2f} (one seed)"


def task_flags(a: argparse.Namespace) -> list[str]:
    return ["--size", str(a.size), "--bits", str(a.bits)]


def study_flags(a: argparse.Namespace, out: Path) -> list[str]:
    return ["--seeds", str(a.seeds), "--episodes", str(a.episodes), "--jobs", str(a.jobs), "--out", str(out)]


def agents_part(a: argparse.Namespace) -> str:
    sections = []
    for n in a.agents:
        out = Path(a.out) / f"agents{n}"
        args = ["compare", *study_flags(a, out), *task_flags(a), "--agents", str(n)]
        bitcomm(*args, threads=a.threads)
        table = (out / "table.md").read_text()
        sections.append(f"### {n} agents on a ring\n\n`bitcomm {' '.join(args)}`\n\n{table}")
    return "\n".join(sections)


def flips_part(a: argparse.Namespace) -> str:
    out = Path(a.out) / "flips"
    vary = "flip_prob=" + ",".join(a.flips)
    args = ["compare", *study_flags(a, out), *task_flags(a), "--techniques", "improved-bitwise", "--vary", vary]
    bitcomm(*args, threads=a.threads)
    # the channel is cut whatever p is, so one no-communication baseline serves every row
    cut = Path(a.out) / "no-comm"
    cut_args = ["compare", *study_flags(a, cut), *task_flags(a), "--techniques", "no-comm"]
    bitcomm(*cut_args, threads=a.threads)
    summary = json.loads((out / "summary.json").read_text())
    rows = []
    for conf in summary["configurations"]:
        p = float(conf["values"]["flip_prob"])
        info, capacity = [], 0.0
        for record in conf["runs"]:
            run = out / record["folder"]
            report: dict[str, Any] = json.loads(
                bitcomm("analyze", str(run), "--json", "--out", str(run / "analysis"), threads=a.threads)
            )
            info.append(report["transmitted_bits"])
            capacity = report["capacity_bits"]
        lengths = [r["sampled"]["mean_episode_length"] for r in conf["runs"]]
        rows.append((p, capacity, _interval(info), _interval(lengths), conf["oracle_mean_episode_length"]))
    lines = [
        f"`bitcomm {' '.join(args)}`, then `bitcomm analyze RUN --json` on every run\n",
        "| flip p | capacity K(1-H(p)) | I(goal; received), bits | episode length (sampled) | oracle |",
        "| ---: | ---: | ---: | ---: | ---: |",
    ]
    for p, cap, info_text, length_text, oracle in sorted(rows):
        lines.append(f"| {p:g} | {cap:.2f} | {info_text} | {length_text} | {oracle:.2f} |")
    for c in json.loads((cut / "summary.json").read_text())["configurations"]:
        length_text = _interval([r["sampled"]["mean_episode_length"] for r in c["runs"]])
        command = "bitcomm " + " ".join(cut_args)
        lines.append(f"\nNo communication (`{command}`): episode length {length_text}.")
    return "### Learning under bit flips (improved + bitwise)\n\n" + "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("all", "agents", "flips"), default="all")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--episodes", type=int, default=15_000, help="budget of every run")
    ap.add_argument("--size", type=int, default=4)
    ap.add_argument("--bits", type=int, default=4)
    ap.add_argument("--agents", type=lambda s: [int(x) for x in s.split(",")], default=[3, 4])
    ap.add_argument("--flips", type=lambda s: s.split(","), default=["0", "0.05", "0.1", "0.2"])
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="runs/channel-demos")
    a = ap.parse_args()
    parts = []
    if a.part in ("all", "agents"):
        parts.append(agents_part(a))
    if a.part in ("all", "flips"):
        parts.append(flips_part(a))
    text = "\n".join(parts)
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / "demos.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
