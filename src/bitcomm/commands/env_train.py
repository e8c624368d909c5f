"""`bitcomm train --env ...` and `bitcomm eval RUN` for runs on a wrapped PettingZoo env (not a subcommand:
`train` and `eval` hand over here when the run is not on the grid)."""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bitcomm.commands.backend_flags import check_resume_flags
from bitcomm.commands.env_flags import ENV_ONLY
from bitcomm.commands.learning_flags import learning_overrides
from bitcomm.errors import bad_value, check_int, plural
from bitcomm.learn.resume_rules import SAVING

if TYPE_CHECKING:
    from bitcomm.envs.vector import EnvLayout
    from bitcomm.learn.env_config import EnvTrainConfig

RENAMED = {"entropy_move": "entropy_action"}
"""Learning flags whose field has another name in `EnvTrainConfig` (the env's own actions are not moves)."""
SUPPORTED = {
    "num_envs", "lr", "critic_lr", "gamma", "entropy_move", "entropy_message", "entropy_message_marginal",
    "max_grad_norm", "epochs", "critic_epochs", "minibatches", "clip", "adv_norm", "checkpoint_seconds",
    "keep_checkpoints", "hidden",
}  # fmt: skip
"""The learning flags that mean something with --env."""


def is_env_run(path: Path | str | None) -> bool:
    """A run folder (by its config.json) trained on a wrapped env."""
    if path is None or not (Path(path) / "config.json").is_file():
        return False
    try:
        record = json.loads((Path(path) / "config.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and isinstance(record.get("env"), str) and "task" not in record


def env_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The learning flags given on the command line, as `EnvTrainConfig` fields; one line for one that does
    not apply to a wrapped env."""
    out: dict[str, Any] = {}
    for name, value in learning_overrides(args).items():
        if name not in SUPPORTED:
            raise bad_value(
                name.replace("_", "-"), value, f"not used with --env (those are: {', '.join(sorted(SUPPORTED))})"
            )
        if name == "hidden":  # one width for both layers; named as typed, not as the pair it becomes
            check_int("hidden", value, 1)
            value = (value, value)
        out[RENAMED.get(name, name)] = value
    return out


GRID_ONLY = ("size", "agents", "max_steps", "observes", "act_fail_prob", "act_delay", "recipients")
"""Task flags of the grid that a wrapped env has no use for (the channel's --bits --delay --flip-prob
--drop-prob apply; who hears whom is --topology)."""


def env_config_from_args(args: argparse.Namespace) -> EnvTrainConfig:
    """The `EnvTrainConfig` the flags describe; estimator, message head and seed are the config's defaults
    where the command has no such flag (`bitcomm compare` sets them per run). A grid-only task flag typed
    with --env is one line (the parser must have been through `mark_task_defaults`)."""
    from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
    from bitcomm.policies.source import given_task_flags

    given = given_task_flags(args)
    for name in GRID_ONLY:
        if name in given:
            raise bad_value(name.replace("_", "-"), given[name], "a grid option, not used with --env")
    channel = EnvChannelConfig(
        bits=int(args.bits), delay=int(args.delay), flip_prob=float(args.flip_prob), drop_prob=float(args.drop_prob),
        topology=args.topology if args.topology is not None else "all", fixed_actions=args.fixed_actions,
    )  # fmt: skip
    extra: dict[str, Any] = {}
    for name in ("episodes", "obs_norm", "env_workers", "estimator", "messages", "seed"):
        if getattr(args, name, None) is not None:
            extra[name] = getattr(args, name)
    learning = env_overrides(args)
    if "minibatches" not in learning and "num_envs" in learning:  # the default follows a smaller batch, as the grid's
        learning["minibatches"] = min(EnvTrainConfig.minibatches, learning["num_envs"])
    return EnvTrainConfig(env=args.env, env_kwargs=args.env_kwargs or {}, channel=channel, **extra, **learning)


def resumed_env_config(args: argparse.Namespace, out: Path) -> EnvTrainConfig:
    """The config of the wrapped-env run in `out`, with the budget, the env's workers and how often it saves as typed
    now; one line for any other flag typed with a value the run was not trained with."""
    from bitcomm.checkpoint import is_env_config, read_config, resolve
    from bitcomm.envs.factory import check_recorded_env
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.run_folder import check_start, resume_config
    from bitcomm.policies.source import given_task_flags

    check_start(out, resume=True)
    if not is_env_config(read_config(out)):  # not "its config does not fit" from a missing key of an env's config
        raise bad_value("out", str(out), "a run of the grid task, not of a wrapped env; resume it without --env")
    cfg = resume_config(out, EnvTrainConfig.from_dict, args.episodes)
    check_recorded_env(cfg.env, resolve(out), getattr(args, "env", None))  # before its module is imported
    typed = {**given_task_flags(args), **env_overrides(args)}  # the grid's task flags are refused below, by name
    for name in ("env", "env_kwargs", "topology", "fixed_actions", "obs_norm", "env_workers", "estimator", "messages"):
        if getattr(args, name, None) is not None:
            typed[name] = getattr(args, name)
    if getattr(args, "seed", None) is not None:
        typed["seed"] = args.seed
    channel = {f.name for f in dataclasses.fields(cfg.channel)}

    def recorded(name: str) -> Any:
        if name in GRID_ONLY:
            raise bad_value(name.replace("_", "-"), typed[name], "a grid option, not used with --env")
        return getattr(cfg.channel if name in channel else cfg, name)

    check_resume_flags(out, typed, recorded)
    now = ("env_workers", *SAVING)  # where the copies are stepped, how often it saves
    return dataclasses.replace(cfg, **{k: typed[k] for k in now if k in typed})


def check_env_eval(cfg: EnvTrainConfig, layout: EnvLayout, episodes: int, flag: str) -> None:
    """An evaluation of `episodes` by a one-hot policy (`evaluate_env`: `EVAL_CHUNK` at a time) whose first step,
    with the float32 tables of 2^K per agent and episode it acts on, would not fit: one line naming `flag`, before
    it plays (as `check_eval` on the grid). Its later steps are `play`'s to refuse, as an episode's length is not
    known in advance (and without one-hot messages, so is its first step)."""
    from bitcomm.commands.flags import check_memory
    from bitcomm.learn.env_eval import EVAL_CHUNK
    from bitcomm.learn.env_rollout import held_step_bytes
    from bitcomm.memory import acting_bytes

    if cfg.messages != "onehot":
        return
    batch = min(episodes, EVAL_CHUNK)
    need = batch * acting_bytes(layout.n, cfg.channel.bits, layout.slots) + held_step_bytes(layout, batch)
    what = f"{batch} episodes side by side with one-hot messages over 2^{cfg.channel.bits} words"
    check_memory(flag, episodes, need, f"{what} ({layout.n} agents hearing {layout.slots} slot(s) each)")


def check_env(configs: Sequence[EnvTrainConfig], processes: int = 1, eval_episodes: int = 0) -> None:
    """Before a line is printed or a folder written: one copy of the runs' env built and its spaces read (a
    module that does not import, a factory that fails, a channel option or a space the learner cannot use is
    one line now, not after the run started), and what `processes` runs at once would hold checked against the
    memory available (as `check_train` on the grid): the networks (their first layers read the observation and
    the state), a batch's first step, and with one-hot messages the 2^K-wide layers and the tables a batch acts
    on; then the evaluation of `eval_episodes` after training (`check_env_eval`, `--eval-episodes`). An episode's
    length is not known in advance: `play` refuses a batch whose later steps would not fit. `configs` share
    their env."""
    from bitcomm.commands.flags import check_memory
    from bitcomm.envs.vector import EnvLayout
    from bitcomm.learn.env_rollout import env_factory, held_step_bytes
    from bitcomm.memory import acting_bytes

    env = env_factory(configs[0])()
    try:
        layout = EnvLayout.of(env)
    finally:
        env.close()
    seen = f"{layout.n} agents observing {layout.obs_dim:,} numbers, a state of {layout.state_size:,}"
    for cfg in configs:
        h = cfg.hidden  # the policy's and the critic's first layers and hidden layers, x16: gradient and Adam
        layers = (layout.obs_dim + layout.state_size) * h[0] + 2 * sum(a * b for a, b in zip(h, h[1:], strict=False))
        hint = ""
        if layout.obs_dim + layout.state_size > h[0]:  # the env's observation, not the width, is what weighs
            hint = "the first layers read every number observed and of the state: give a narrower --hidden or an env"
            hint += " that observes fewer"
        what = f"the networks ({seen}; {processes} run(s) at once)"
        check_memory("hidden", h[0], processes * layers * 16, what, hint)
        batch = processes * cfg.num_envs
        buffers = processes * layers * 16 + held_step_bytes(layout, batch, learning=True)
        onehot = 0
        if cfg.messages == "onehot":  # the policy's output and message input, V1's message input (x16: Adam)
            readers = 2 if cfg.estimator == "standard" else 1
            wide = processes * (1 << cfg.channel.bits) * (h[-1] + readers * layout.slots * h[0]) * 16
            onehot = wide + batch * acting_bytes(layout.n, cfg.channel.bits, layout.slots)
        if onehot > buffers:
            what = f"one-hot messages over 2^{cfg.channel.bits} words ({processes} run(s) at once)"
            check_memory("bits", cfg.channel.bits, onehot + buffers, what)
        else:
            what = f"{batch} episodes side by side, for one step ({seen})"
            check_memory("num-envs", cfg.num_envs, onehot + buffers, what)
        if eval_episodes:
            check_env_eval(cfg, layout, eval_episodes, "eval-episodes")


def train(args: argparse.Namespace, threads: int | None = None) -> int:
    """Train on the env of `--env` (or resume such a run), on the torch threads the caller has set (`threads`, as
    `use_threads` chose them; None: OMP_NUM_THREADS's)."""
    from bitcomm.learn.env_eval import evaluate_env
    from bitcomm.learn.env_run import train_env
    from bitcomm.learn.run_folder import check_start

    if getattr(args, "address", None) is not None:  # the Ray backend trains the grid only
        raise bad_value("address", args.address, "not used with --env")
    if getattr(args, "recipe", None) is not None:
        raise bad_value("recipe", args.recipe, "not used with --env (its learning options are flags of their own)")
    if args.resume:
        if args.out is None:
            raise bad_value("resume", True, "give the run folder with --out")
        cfg = resumed_env_config(args, args.out)
    else:
        cfg = env_config_from_args(args)
    module = cfg.env.partition(":")[0].rpartition(".")[2]
    out = args.out or Path("runs") / f"env-{module}-{cfg.estimator}-{cfg.messages}-s{cfg.seed}"
    check_start(out, args.resume)  # before a line is printed
    check_env([cfg], eval_episodes=args.eval_episodes)  # the final evaluation's, before training rather than after
    print(
        f"run folder: {out}{' (resumed)' if args.resume else ''}; env {cfg.env}; "
        f"torch threads: {threads or 'OMP_NUM_THREADS'}",
        flush=True,
    )
    checkpoint = train_env(cfg, out, resume=args.resume, progress=not args.quiet)
    print(f"checkpoint: {checkpoint}")
    if args.eval_episodes:
        result = evaluate_env(checkpoint, args.eval_episodes, cfg.seed, typed_env=cfg.env)  # typed, or checked above
        print_env_result(result, False, f"eval (sampling, seed {cfg.seed})")
    return 0


def check_env_only(args: argparse.Namespace) -> None:
    """Without --env, the flags that only a wrapped env reads are refused (one line)."""
    for name in ENV_ONLY:
        value = getattr(args, name, None)
        if value is not None:
            raise bad_value(name.replace("_", "-"), value, "only with --env PACKAGE.MODULE:FACTORY")


def drop_prob_of(args: argparse.Namespace) -> float | None:
    """The --drop-prob typed for a command on a wrapped-env run (None: the run's own); the other task flags
    change the grid, so one of them is one line."""
    from bitcomm.policies.source import given_task_flags

    given = given_task_flags(args)
    other = sorted(set(given) - {"drop_prob"})
    if other:
        raise bad_value(other[0].replace("_", "-"), given[other[0]], "a run on a wrapped env takes only --drop-prob")
    return given.get("drop_prob")


def evaluate(args: argparse.Namespace) -> int:
    """`bitcomm eval RUN` on a wrapped-env run: only --drop-prob of the task flags applies."""
    from bitcomm.learn.env_eval import evaluate_env_policy, load_env_policy

    drop_prob = drop_prob_of(args)
    cfg, policy = load_env_policy(args.run_path)
    check_env_eval(cfg, policy.layout, args.episodes, "episodes")
    result = evaluate_env_policy(cfg, policy, args.episodes, args.seed, drop_prob, greedy=args.greedy)
    print_env_result(result, args.json, f"{args.run_path} ({'greedy' if args.greedy else 'sampling'})")
    return 0


def print_env_result(result: Any, as_json: bool, title: str) -> None:
    if as_json:
        print(json.dumps(result.to_dict()))
        return

    (rlo, rhi), (llo, lhi) = result.return_ci95, result.length_ci95
    print(
        f"{title}: {plural(result.episodes, 'episode', 'episodes')}, mean team return {result.mean_team_return:.3f} "
        f"(95% CI {rlo:.3f} to {rhi:.3f}), mean episode length {result.mean_episode_length:.2f} "
        f"(95% CI {llo:.2f}-{lhi:.2f})"
    )
