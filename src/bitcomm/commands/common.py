"""Flags shared by every command that runs the task (the environment and the channel), and the record of what
made a study's files (`write_provenance`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from bitcomm import provenance
from bitcomm.commands.flags import integer, number
from bitcomm.config import MAX_AGENTS, MAX_SIZE, MAX_STEPS, ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import plural

if TYPE_CHECKING:
    from bitcomm.policies.evaluation import EvalResult

PROBABILITY = number(0.0, 1.0)


def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(",") if x.strip() != "")
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: expected comma-separated agent numbers") from None


def _groups(text: str) -> tuple[tuple[int, ...], ...]:
    return tuple(_int_list(group) for group in text.split(";"))


RUN_TASK = (
    "A run (or an exported policy) is played on its own task: a flag typed changes that option alone (the defaults "
    "shown serve the oracle and random policies)."
)
"""The task group's description in a command that reads a run (`resolve_task`), whose help gave the grid's defaults
as if they were what `eval RUN` plays."""


def add_task_flags(parser: argparse.ArgumentParser, reads_runs: bool = False) -> None:
    """Every environment and channel parameter of SPEC sections 1 and 2, with its default (`reads_runs`: a command
    that plays a run's own task where no flag is typed, which its help then says)."""
    env, ch = EnvConfig(), ChannelConfig()
    g = parser.add_argument_group("task (environment and channel)", RUN_TASK if reads_runs else None)
    g.add_argument("--size", type=integer(2, MAX_SIZE), default=env.size, help="grid side (default %(default)s)")
    g.add_argument(
        "--agents", type=integer(2, MAX_AGENTS), default=env.n_agents, help="number of agents (default %(default)s)"
    )
    g.add_argument(
        "--max-steps", type=integer(1, MAX_STEPS), default=env.max_steps, help="truncation length (default %(default)s)"
    )
    g.add_argument(
        "--observes", type=_int_list, default=None, help="whose goal each agent sees, e.g. 1,0 (default: ring)"
    )
    g.add_argument("--bits", type=integer(1, 30), default=ch.bits, help="message bits K (default %(default)s)")
    g.add_argument(
        "--recipients",
        type=_groups,
        default=None,
        help="who hears each agent, e.g. '1,2;0;0' (default: whose goal it sees)",
    )
    g.add_argument(
        "--delay",
        type=integer(1, MAX_STEPS),
        default=ch.delay,
        help="message delay in steps, less than --max-steps (default %(default)s)",
    )
    g.add_argument("--flip-prob", type=PROBABILITY, default=ch.flip_prob, help="bit flip probability")
    g.add_argument("--drop-prob", type=PROBABILITY, default=ch.drop_prob, help="message drop probability")
    g.add_argument("--act-fail-prob", type=PROBABILITY, default=env.act_fail_prob, help="actuation: move not executed")
    g.add_argument(
        "--act-delay",
        type=integer(0, MAX_STEPS),
        default=env.act_delay,
        help="actuation: steps before a move takes effect, less than --max-steps",
    )


def task_from_args(args: argparse.Namespace) -> TaskConfig:
    env = EnvConfig(
        size=args.size,
        n_agents=args.agents,
        max_steps=args.max_steps,
        observes=args.observes,
        act_fail_prob=args.act_fail_prob,
        act_delay=args.act_delay,
    )
    channel = ChannelConfig(
        bits=args.bits, recipients=args.recipients, delay=args.delay, flip_prob=args.flip_prob, drop_prob=args.drop_prob
    )
    return TaskConfig(env, channel)


def check_episodes(episodes: int) -> int:
    """Evaluation episodes (parsed by `flags.EVAL_EPISODES`; checked again for callers that build args)."""
    from bitcomm.commands.flags import check_episodes as check

    return check(episodes)


def print_result(result: EvalResult, as_json: bool, title: str) -> None:
    """`--json`: one object; otherwise a short human summary."""
    if as_json:
        json.dump(result.to_dict(), sys.stdout)
        sys.stdout.write("\n")
        return

    lo, hi = result.ci95
    print(
        f"{title}: {plural(result.episodes, 'episode', 'episodes')}, "
        f"mean episode length {result.mean_episode_length:.2f} (95% CI {lo:.2f}-{hi:.2f}), "
        f"mean team return {result.mean_team_return:.3f}, "
        f"success rate {result.success_rate:.3f}"
    )


def write_provenance(args: argparse.Namespace, out: Path | str, task: TaskConfig | None = None) -> Path:
    """`<out>/provenance.json` beside a study's results: its flags as parsed (defaults included), and the code,
    libraries, machine and command that made the files (`bitcomm.provenance.record`), so a figure can be traced
    as a training run's config.json traces it. With `task` (the task played, a RUN's where one is read), the task
    flags not typed are left out: their defaults are not what played."""
    from bitcomm.policies.source import TASK_FLAGS, given_task_flags

    typed = given_task_flags(args)
    settings = {
        k: v for k, v in vars(args).items() if not callable(v) and (task is None or k not in TASK_FLAGS or k in typed)
    }
    if task is not None:
        settings["task"] = task.to_dict()
    return provenance.write(Path(out), settings)
