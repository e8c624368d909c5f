"""`bitcomm deploy [RUN | --onnx FILE]`: one process per agent, messages as UDP datagrams on loopback (see
`bitcomm.deploy`). With `--onnx`, each agent process holds only its own onnxruntime session (no torch)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from bitcomm.commands.common import add_task_flags
from bitcomm.commands.flags import (
    MAX_DEADLINE_MS,
    MAX_SECONDS,
    SEED,
    add_threads_flag,
    check_eval,
    integer,
    number,
    use_threads,
)
from bitcomm.policies.source import add_policy_flags, source_from_args

if TYPE_CHECKING:
    from bitcomm.deploy import EpisodeOutcome
    from bitcomm.policies.evaluation import EvalResult

MAX_DEPLOY_EPISODES = 100_000
"""Each deployed episode is a few hundred UDP round trips: 10^5 episodes is already hours."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "deploy",
        help="run the agents as separate processes talking over UDP, against the simulator",
        description="One world process and one process per agent; messages travel as UDP datagrams on 127.0.0.1. "
        "--drop-prob and --flip-prob act on the wire (seeded, by the sender); a message missing at its deadline "
        "reads as zeros. The summary compares with the same policy on the same episodes in the vectorized simulator.",
    )
    p.add_argument(
        "--episodes",
        type=integer(1, MAX_DEPLOY_EPISODES, "hours of UDP round trips at the top"),
        default=100,
        help="episodes to play (default %(default)s)",
    )
    p.add_argument("--seed", type=SEED, default=0, help="seed of the episode set and the noise (default %(default)s)")
    p.add_argument(
        "--deadline-ms",
        type=number(0.0, MAX_DEADLINE_MS, strict=True),
        default=20.0,
        help="wait for a step's messages (default %(default)s)",
    )
    p.add_argument(
        "--timeout",
        type=number(0.0, MAX_SECONDS, strict=True),
        default=300.0,
        help="bound on the whole run, seconds (default %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object (episode lines go to stderr)")
    add_threads_flag(
        p,
        "; this process's, which builds the policy and plays the simulator's comparison: each agent process runs "
        "on 1 thread whatever this says (it acts on one observation at a time, and the agents already take a core "
        "each)",
    )
    add_task_flags(p, reads_runs=True)
    add_policy_flags(p, onnx=True)
    p.set_defaults(run=run)


def _line(result: EvalResult) -> str:
    lo, hi = result.ci95
    return (
        f"mean episode length {result.mean_episode_length:.2f} (95% CI {lo:.2f}-{hi:.2f}), "
        f"mean team return {result.mean_team_return:.3f}, success rate {result.success_rate:.3f}"
    )


def run(args: argparse.Namespace) -> int:
    from bitcomm.deploy import DeployError, DeployResult, run_deploy
    from bitcomm.policies.agent_policies import BatchedPolicy
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.stop_signals import repeats_count_once, sigterm_interrupts

    episodes = args.episodes
    source = source_from_args(args)
    task = source.task_from_args(args)
    check_eval(task, episodes, onehot=source.onehot())
    use_threads(args)
    source.build(task)  # a policy that cannot be built fails here, with one line, before any process starts
    log = sys.stderr if args.json else sys.stdout

    played: list[EpisodeOutcome] = []

    def report(o: EpisodeOutcome) -> None:
        played.append(o)
        status = "on goals" if o.success else "truncated"
        print(f"episode {o.index}: {o.length} steps, {1000 * o.wall_s:.1f} ms, {status}", file=log, flush=True)

    def summarise_played() -> None:
        """The episodes played before the run stopped, as the summary would read them."""
        if played:
            summary = DeployResult(played, task.env.max_steps).summary
            print(f"deployed, {len(played)} of {episodes} episodes before it stopped: {_line(summary)}", file=log)

    # `kill PID` or a scheduler's limit stops it as Ctrl-C does, with its summary; `timeout`'s second copy, to the
    # process group, must not cut the agents' shutdown or the summary short
    with sigterm_interrupts(), repeats_count_once():
        try:
            result = run_deploy(source, task, episodes, args.seed, args.deadline_ms, args.timeout, on_episode=report)
            simulated = evaluate(BatchedPolicy(source.build(task, seed=args.seed)), task, episodes, args.seed)
        except DeployError as err:
            summarise_played()
            print(f"bitcomm deploy: error: {err}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: what was played still counts; `bitcomm.cli` says it stopped
            summarise_played()
            raise
    deployed = result.summary
    if args.json:
        out = deployed.to_dict()
        out.update(simulator=simulated.to_dict(), network=result.network, startup_s=result.startup_s,
                   wall_s=result.wall_s)  # fmt: skip
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    net = result.network
    print(f"deployed  ({task.env.n_agents} agent processes, UDP): {_line(deployed)}")
    print(f"simulator (same policy, same episodes):  {_line(simulated)}")
    print(
        f"datagrams: {net.get('sent', 0)} sent, {net.get('dropped', 0)} dropped on purpose, "
        f"{net.get('send_failed', 0)} failed to send, {net.get('received', 0)} received, "
        f"{net.get('missing', 0)} missing at their deadline, {net.get('late', 0)} late, "
        f"{net.get('duplicate', 0)} duplicate, {net.get('foreign', 0)} foreign; "
        f"startup {result.startup_s:.1f} s, total {result.wall_s:.1f} s"
    )
    return 0
