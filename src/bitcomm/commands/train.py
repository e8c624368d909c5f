"""`bitcomm train`: learn to act and to talk (SPEC section 5); writes a run folder (see bitcomm.train.run).

Learning options (`bitcomm.commands.learning_flags`, one per plain field of TrainConfig and ModelConfig)
default to None, meaning "the recipe's value" (`--recipe fast|paper`); a flag typed on the command line
overrides the recipe. `--resume` continues the run in `--out` from its latest checkpoint with the
config it was started with (only `--episodes`, a new budget, may change).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bitcomm.commands.common import add_task_flags, task_from_args
from bitcomm.commands.learning_flags import add_learning_flags, learning_overrides
from bitcomm.errors import bad_value


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train agents to act and communicate")
    p.add_argument("--estimator", choices=("standard", "improved"), default="improved", help="default %(default)s")
    p.add_argument("--messages", choices=("bitwise", "onehot"), default="bitwise", help="default %(default)s")
    p.add_argument("--recipe", choices=("paper", "fast"), default="fast", help="learning options (default %(default)s)")
    p.add_argument("--episodes", type=int, default=None, help="budget of environment episodes")
    p.add_argument("--seed", type=int, default=0, help="default %(default)s")
    p.add_argument(
        "--out", type=Path, default=None, help="run folder (default runs/<recipe>-<estimator>-<messages>-s<seed>)"
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument(
        "--eval-episodes", type=int, default=1000, help="final evaluation episodes, 0: none (default %(default)s)"
    )
    add_learning_flags(p)
    add_task_flags(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from bitcomm.train.config import make_train_config
    from bitcomm.train.run import resume_config, train

    if args.threads is not None:
        if args.threads < 1:
            raise bad_value("threads", args.threads, "must be an integer >= 1")
        import torch

        torch.set_num_threads(args.threads)
    out = args.out or Path("runs") / f"{args.recipe}-{args.estimator}-{args.messages}-s{args.seed}"
    if args.eval_episodes < 0:
        raise bad_value("eval-episodes", args.eval_episodes, "must be an integer >= 0")
    if args.resume:
        if args.episodes is not None and args.episodes < 1:
            raise bad_value("episodes", args.episodes, "must be an integer >= 1")
        cfg = resume_config(out, args.episodes)
    else:
        cfg = make_train_config(
            args.recipe,
            task_from_args(args),
            estimator=args.estimator,
            messages=args.messages,
            seed=args.seed,
            episodes=args.episodes,
            **learning_overrides(args),
        )
    print(f"run folder: {out}", flush=True)
    checkpoint = train(cfg, out, resume=args.resume, progress=not args.quiet)
    print(f"checkpoint: {checkpoint}")
    if args.eval_episodes:
        from bitcomm.agent_policies import BatchedPolicy, ControllerAgent
        from bitcomm.commands.common import print_result
        from bitcomm.controller import Controller
        from bitcomm.evaluation import evaluate

        controller = Controller.load(checkpoint, seed=cfg.seed)
        result = evaluate(BatchedPolicy(ControllerAgent(controller)), cfg.task, args.eval_episodes, cfg.seed)
        print_result(result, False, f"eval (sampling, seed {cfg.seed})")
    return 0
