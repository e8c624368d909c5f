"""`bitcomm eval RUN_OR_CHECKPOINT`: measure a trained policy, with the JSON keys of `bitcomm baseline`.

The task is the one the policy was trained on; task flags typed on the command line change it, so a
policy trained clean can be measured under noise, drops or delay. Grid size and bits must match the network, and
each agent must hear as many senders as in training; the number of agents may change, since one network acts for
each of them (a policy trained by 2 may play a ring of 3). Acting goes through `bitcomm.Controller`, as a deployed
robot would.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from bitcomm.commands.common import add_task_flags, print_result
from bitcomm.commands.flags import EVAL_EPISODES, SEED, add_threads_flag, check_eval, use_threads

if TYPE_CHECKING:
    from bitcomm.policies.evaluation import EvalResult


def add_parser(sub: argparse._SubParsersAction) -> None:
    from bitcomm.policies.source import mark_task_defaults

    p = sub.add_parser("eval", help="evaluate a trained policy (run folder, checkpoint file or exported .onnx)")
    p.add_argument(
        "run_path", metavar="RUN_OR_CHECKPOINT", help="run folder, .safetensors file, or .onnx file of bitcomm export"
    )
    p.add_argument("--episodes", type=EVAL_EPISODES, default=2000, help="evaluation episodes (default %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the episode set and of sampling (default %(default)s)")
    p.add_argument("--greedy", action="store_true", help="most likely move and message instead of sampling")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_threads_flag(p)
    add_task_flags(p, reads_runs=True)
    mark_task_defaults(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from bitcomm.commands import env_train
    from bitcomm.learn.env_run import env_run_config
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate_controller
    from bitcomm.policies.source import POLICY_INPUTS, resolve_task

    use_threads(args)
    if str(args.run_path).endswith(".onnx"):
        result = evaluate_onnx(args)
    elif env_run_config(args.run_path) is not None:
        return env_train.evaluate(args)
    else:
        controller = Controller.load(args.run_path, seed=args.seed)
        task = resolve_task(args, controller.task, label=f"RUN {args.run_path!r}", fixed=POLICY_INPUTS)
        check_eval(task, args.episodes, onehot=controller.messages == "onehot")
        result = evaluate_controller(controller, args.episodes, args.seed, args.greedy, task)
    print_result(result, args.json, f"{args.run_path} ({'greedy' if args.greedy else 'sampling'})")
    return 0


def evaluate_onnx(args: argparse.Namespace) -> EvalResult:
    """An exported policy on the simulator, run by onnxruntime as a robot runs it: its greedy play is the run's
    to the step; sampled play draws from numpy's stream, not torch's, so it matches in distribution."""
    from bitcomm.policies.agent_policies import BatchedPolicy
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.source import PolicySource

    source = PolicySource("onnx", greedy=args.greedy, onnx=args.run_path)
    task = source.task_from_args(args)
    check_eval(task, args.episodes, onehot=source.onehot())
    return evaluate(BatchedPolicy(source.build(task, seed=args.seed)), task, args.episodes, args.seed)
