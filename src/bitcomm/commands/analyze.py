"""`bitcomm analyze [RUN]`: what each bit means and how much of the goal gets through
(see `bitcomm.studies.analysis`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bitcomm.commands.common import add_task_flags, write_provenance
from bitcomm.commands.flags import (
    MAX_BATCH,
    MAX_SAMPLES,
    SEED,
    add_threads_flag,
    check_play,
    integer,
    out_dir,
    use_threads,
)
from bitcomm.files import write_text_atomic
from bitcomm.policies.source import add_policy_flags, source_from_args
from bitcomm.stop_signals import sigterm_interrupts


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "analyze",
        help="mutual information of each bit with the goal, decoder accuracy, heatmaps",
        description="Per-bit mutual information with the sender's observed goal, information transmitted "
        "through the channel against its capacity, a lookup decoder, heatmaps (PNG) and a Markdown summary.",
    )
    p.add_argument(
        "--out", type=out_dir, default="analysis", help="folder for bits.png and summary.md (default %(default)s)"
    )
    p.add_argument(
        "--samples",
        type=integer(100, MAX_SAMPLES, "minutes of play and a few hundred MB at the top"),
        default=200_000,
        help="deliveries (message x recipient) to send in time to arrive; fewer arrive where an episode ends "
        "first (default %(default)s)",
    )
    p.add_argument(
        "--envs", type=integer(1, MAX_BATCH), default=1024, help="episodes played side by side (default %(default)s)"
    )
    p.add_argument("--seed", type=SEED, default=0, help="seed of play and of the decoder's split (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the summary figures as one JSON object")
    add_threads_flag(p)
    add_task_flags(p, reads_runs=True)
    add_policy_flags(p)
    p.set_defaults(run=run)


@sigterm_interrupts()  # from its first line: `timeout` or a scheduler stops it as Ctrl-C does, exit 143
def run(args: argparse.Namespace) -> int:
    from bitcomm.studies.analysis import analyze_samples, bit_maps, collect_messages, markdown_summary, save_heatmaps

    source = source_from_args(args)
    task = source.task_from_args(args)
    check_play(task, "envs", args.envs, args.envs, onehot=source.onehot())
    use_threads(args)
    samples = collect_messages(source.build(task, seed=args.seed), task, args.samples, args.envs, args.seed)
    report = analyze_samples(samples, task, source.label, args.seed)
    out = Path(args.out)
    heatmaps = save_heatmaps(bit_maps(samples, task), out / "bits.png", f"{source.label}: P(bit = 1) by observed goal")
    summary = out / "summary.md"
    write_text_atomic(summary, markdown_summary(report, heatmaps.name))
    write_provenance(args, out, task)
    if args.json:
        json.dump(report.to_dict(), sys.stdout)
        sys.stdout.write("\n")
        return 0
    r = report
    print(
        f"{source.label}: {r.transmitted_bits:.2f} bits of the goal transmitted (H(goal) {r.goal_entropy_bits:.2f}, "
        f"capacity {r.capacity_bits:.2f}); lookup decoder accuracy {r.decoder_accuracy:.3f}"
    )
    for b in r.per_bit:
        print(f"  bit {b.bit}: I(row) {b.mi_row:.3f}  I(column) {b.mi_col:.3f}  I(cell) {b.mi_cell:.3f}")
    print(f"wrote {heatmaps}, {summary} and provenance.json")
    return 0
