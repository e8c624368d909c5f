"""`bitcomm baseline`: measure a reference policy (oracle or random) on the task."""

from __future__ import annotations

import argparse

from bitcomm.commands.common import add_task_flags, print_result, task_from_args
from bitcomm.commands.flags import EVAL_EPISODES, SEED, check_eval
from bitcomm.policies.evaluation import evaluate
from bitcomm.policies.reference import REFERENCE_POLICIES, make_reference_policy


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("baseline", help="evaluate a reference policy (oracle or random)")
    p.add_argument("--policy", choices=REFERENCE_POLICIES, default="oracle", help="reference policy")
    p.add_argument("--episodes", type=EVAL_EPISODES, default=2000, help="evaluation episodes (default %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the episode set (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_task_flags(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    task = task_from_args(args)
    check_eval(task, args.episodes)
    policy = make_reference_policy(args.policy, task, seed=args.seed)
    result = evaluate(policy, task, args.episodes, args.seed)
    print_result(result, args.json, args.policy)
    return 0
