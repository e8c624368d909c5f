"""`bitcomm render [RUN] --out episode.gif`: an animation of one episode (see `bitcomm.studies.render`; for a
run trained on a wrapped PettingZoo env, `bitcomm.studies.env_render`)."""

from __future__ import annotations

import argparse

from bitcomm.commands.common import add_task_flags
from bitcomm.commands.flags import (
    MAX_FPS,
    MAX_FRAMES,
    MIN_FPS,
    SEED,
    add_threads_flag,
    gif_file,
    number,
    out_dir,
    use_threads,
)
from bitcomm.errors import bad_value
from bitcomm.policies.source import add_policy_flags, source_from_args
from bitcomm.stop_signals import sigterm_interrupts


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render",
        help="animate one episode as a GIF (and PNG frames)",
        description="One frame per step, showing the state after that step: agents, goals, paths, "
        "and the bits sent and received. For a run trained with --env: the env's own picture and each agent's "
        "bits (only --drop-prob of the task flags applies).",
    )
    p.add_argument("--out", type=gif_file, default="episode.gif", help="GIF to write (default %(default)s)")
    p.add_argument(
        "--frames-dir",
        type=out_dir,
        default=None,
        help="also write one PNG per step into this folder (default: no PNGs)",
    )
    p.add_argument("--seed", type=SEED, default=0, help="picks the episode (default %(default)s)")
    p.add_argument(
        "--fps",
        type=number(MIN_FPS, MAX_FPS),
        default=2.0,
        help="frames per second of the GIF (default %(default)s)",
    )
    add_threads_flag(p, "; only a trained RUN plays on torch: the oracle and random policies never load it")
    add_task_flags(p, reads_runs=True)
    add_policy_flags(p)
    p.set_defaults(run=run)


@sigterm_interrupts()  # from its first line: a stop leaves no half-written file, nor its temporary
def run(args: argparse.Namespace) -> int:
    from bitcomm.studies.render import record_episode, render_frames, save_gif, save_png_frames

    source = source_from_args(args)
    if source.name == "run":
        from bitcomm.learn.env_run import env_run_config

        use_threads(args)
        if env_run_config(args.run_path) is not None:
            return run_env(args)
    task = source.task_from_args(args)
    if task.env.max_steps > MAX_FRAMES:
        raise bad_value("max-steps", task.env.max_steps, f"render draws one frame per step: at most {MAX_FRAMES}")
    record = record_episode(source.build(task, seed=args.seed), task, seed=args.seed)
    frames = render_frames(record)
    gif = save_gif(frames, args.out, fps=args.fps)
    outcome = "all agents on their goals" if record.success else f"truncated at {task.env.max_steps}"
    print(f"{source.label}: episode of {record.length} steps ({outcome}); wrote {gif} ({len(frames)} frames)")
    if args.frames_dir:
        paths = save_png_frames(frames, args.frames_dir)
        print(f"wrote {len(paths)} PNG frames to {args.frames_dir}")
    return 0


def run_env(args: argparse.Namespace) -> int:
    """`render RUN` on a run trained on a wrapped env: the episode `bitcomm eval RUN --seed S --episodes 1` plays."""
    from bitcomm.commands.env_train import drop_prob_of
    from bitcomm.studies.env_render import record_env_episode, render_env_frames
    from bitcomm.studies.render import save_gif, save_png_frames

    record = record_env_episode(
        args.run_path, args.seed, greedy=args.greedy, drop_prob=drop_prob_of(args), max_frames=MAX_FRAMES
    )
    frames = render_env_frames(record)
    gif = save_gif(frames, args.out, fps=args.fps)
    mode = "greedy" if args.greedy else "sampling"
    print(
        f"{args.run_path} ({record.env}, {mode}): episode of {record.length} steps, team return "
        f"{record.team_rewards.sum():+.3f}; wrote {gif} ({len(frames)} frames)"
    )
    if args.frames_dir:
        paths = save_png_frames(frames, args.frames_dir)
        print(f"wrote {len(paths)} PNG frames to {args.frames_dir}")
    return 0
