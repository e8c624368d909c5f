"""`bitcomm train`: learn to act and to talk (SPEC section 5); writes a run folder (see bitcomm.learn.run_folder).

Learning options (`bitcomm.commands.learning_flags`, one per plain field of TrainConfig and ModelConfig)
default to None, meaning "the recipe's value" (`--recipe reinforced|supervised|paper`); a flag typed on the command line
overrides the recipe. `--resume` continues the run in `--out` from its latest checkpoint with the
config it was started with (only `--episodes`, a new budget, may change, and where it runs: `--backend`,
default local, `--workers`, `--staleness`; see `bitcomm.commands.backend_flags`).
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bitcomm.commands import env_train
from bitcomm.commands.backend_flags import add_backend_flags, check_resume_flags, execution
from bitcomm.commands.common import add_task_flags, task_from_args
from bitcomm.commands.env_flags import add_env_flags
from bitcomm.commands.flags import (
    MAX_EVAL_EPISODES,
    MAX_TRAIN_EPISODES,
    SEED,
    add_threads_flag,
    check_eval,
    check_train,
    integer,
    out_dir,
    use_threads,
)
from bitcomm.commands.learning_flags import add_learning_flags, learning_overrides
from bitcomm.errors import bad_value
from bitcomm.learn.options import field_default
from bitcomm.learn.recipes import DEFAULT_RECIPE, RECIPES
from bitcomm.learn.resume_rules import SAVING

if TYPE_CHECKING:
    from bitcomm.config import TaskConfig
    from bitcomm.learn.config import TrainConfig

GRID_CONFIG = ("bitcomm.learn.config", "TrainConfig")
ENV_CONFIG = ("bitcomm.learn.env_config", "EnvTrainConfig")
"""Where the two budgets' defaults are read from (without importing torch)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    from bitcomm.policies.source import mark_task_defaults

    p = sub.add_parser("train", help="train agents to act and communicate")
    # None: not typed (the defaults below), which a resume tells from a typed value (`check_resume_flags`)
    p.add_argument("--estimator", choices=("standard", "improved"), default=None, help="default improved")
    p.add_argument("--messages", choices=("bitwise", "onehot"), default=None, help="default bitwise")
    p.add_argument(
        "--recipe", choices=tuple(RECIPES), default=None, help=f"learning options (default {DEFAULT_RECIPE})"
    )
    p.add_argument(
        "--episodes",
        type=integer(1, MAX_TRAIN_EPISODES, "beyond 10^9 a run takes years"),
        default=None,
        help=f"budget of environment episodes, played in whole batches of --num-envs (default "
        f"{field_default(*GRID_CONFIG, 'episodes'):,}; with --env {field_default(*ENV_CONFIG, 'episodes'):,})",
    )
    p.add_argument("--seed", type=SEED, default=None, help="default 0")
    p.add_argument(
        "--out",
        type=out_dir,
        default=None,
        help="run folder (default runs/<recipe>-<estimator>-<messages>-s<seed>; with --env "
        "runs/env-<module>-<estimator>-<messages>-s<seed>, <module> the last part of the env's module)",
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_threads_flag(
        p,
        "; in sync mode 2 or more run the critic's step beside the policy's, half the threads each, so a run on "
        "2 threads is the run on 1 bit for bit and a busy core does not stall it (before, with one other busy "
        "core, 2 threads trained 2.9x slower than 1)",
    )
    p.add_argument(
        "--eval-episodes",
        type=integer(0, MAX_EVAL_EPISODES),
        default=1000,
        help="final evaluation episodes, 0: none (default %(default)s)",
    )
    add_learning_flags(p)
    add_backend_flags(p)
    add_task_flags(p)
    add_env_flags(p)
    mark_task_defaults(p)  # a grid-only flag typed with --env is refused
    p.set_defaults(run=run)


STRUCTURAL_DEFAULTS = {"recipe": DEFAULT_RECIPE, "estimator": "improved", "messages": "bitwise", "seed": 0}
"""What a run is trained as when its flag is not typed."""


MEANT: dict[str, Callable[[TaskConfig], Any]] = {
    "observes": lambda task: tuple(task.env.observed),
    "recipients": lambda task: task.recipient_matrix.tolist(),
}
"""The task flags whose value may be left to a default that stands for it, by what they mean."""


def typed_structure(args: argparse.Namespace) -> dict[str, Any]:
    """The flags of `STRUCTURAL_DEFAULTS` typed on the command line."""
    return {name: getattr(args, name) for name in STRUCTURAL_DEFAULTS if getattr(args, name) is not None}


def resumed_config(args: argparse.Namespace, out: Path) -> TrainConfig:
    """The config of the run in `out`, with the budget and how often it saves as typed now; one line for any other
    flag typed with a value the run was not trained with."""
    from bitcomm.learn.config import MODEL_OPTIONS, TrainConfig
    from bitcomm.learn.run_folder import resume_config
    from bitcomm.policies.source import TASK_FLAGS, given_task_flags, resolve_task

    cfg = resume_config(out, TrainConfig.from_dict, args.episodes)
    task = resolve_task(args, cfg.task)

    def recorded(name: str, of: Any = cfg.task) -> Any:
        if name in MEANT:  # a default (None: the ring) and the map it stands for are the same run
            return MEANT[name](of)
        if name in TASK_FLAGS:
            part, field = TASK_FLAGS[name]
            return getattr(getattr(of, part), field)
        return getattr(cfg.model if name in MODEL_OPTIONS else cfg, name)

    overrides = learning_overrides(args)
    typed = {**typed_structure(args), **overrides, **{d: recorded(d, task) for d in given_task_flags(args)}}
    check_resume_flags(out, typed, recorded)
    saving = {k: v for k, v in overrides.items() if k in SAVING}
    return dataclasses.replace(cfg, **saving)  # type: ignore[arg-type]


def run(args: argparse.Namespace) -> int:
    from bitcomm.learn.config import make_train_config
    from bitcomm.learn.run import check_run, train_checked
    from bitcomm.learn.run_folder import check_start

    if args.env is not None or (args.resume and env_train.is_env_run(args.out)):
        return env_train.train(args, use_threads(args))
    env_train.check_env_only(args)
    structure = {**STRUCTURAL_DEFAULTS, **typed_structure(args)}
    out = args.out or Path("runs") / "{recipe}-{estimator}-{messages}-s{seed}".format(**structure)
    if args.resume:
        cfg = resumed_config(args, out)
    else:
        check_start(out, resume=False)  # before a line is printed
        cfg = make_train_config(
            structure.pop("recipe"),
            task_from_args(args),
            episodes=args.episodes,
            **structure,
            **learning_overrides(args),
        )
    if args.workers is not None and args.backend != "ray" and cfg.mode != "a3c":
        raise bad_value("workers", args.workers, "acts only with --mode a3c or --backend ray")
    cfg = execution(args, cfg)
    check_train(cfg)
    if args.eval_episodes:  # the final evaluation's, before training rather than after it
        check_eval(cfg.task, args.eval_episodes, cfg.model.messages == "onehot", "eval-episodes")
    out = check_run(cfg, out, args.resume, args.address)  # before this line: a run refused must not name its folder
    threads = use_threads(args)
    print(
        f"run folder: {out}{' (resumed)' if args.resume else ''}; torch threads: {threads or 'OMP_NUM_THREADS'}",
        flush=True,
    )
    checkpoint = train_checked(cfg, out, args.resume, not args.quiet, args.address)
    print(f"checkpoint: {checkpoint}")
    if args.eval_episodes:
        from bitcomm.commands.common import print_result
        from bitcomm.policies.evaluation import evaluate_checkpoint

        result = evaluate_checkpoint(checkpoint, args.eval_episodes, cfg.seed, task=cfg.task)
        print_result(result, False, f"eval (sampling, seed {cfg.seed})")
    return 0
