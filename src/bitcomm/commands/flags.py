"""Argument types and limits of the `bitcomm` command line, in one place.

Each type refuses a bad value while argparse parses, so a command fails with one line naming the
flag, the value and what is allowed (`argument --seed: invalid value '-1': ...`, exit status 2)
before any work starts. The limits bound what one command may ask of one machine: a size whose
buffers would not fit in memory is refused up front with the estimate (`check_memory`), and counts
that only make a command run for days have a documented cap. No heavy imports: every command
builds every parser.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from bitcomm.config import MAX_EVAL_EPISODES, MAX_JOBS, MAX_SEED
from bitcomm.errors import bad_value
from bitcomm.memory import BYTES_PER_GB, acting_bytes, available_bytes

if TYPE_CHECKING:
    from bitcomm.config import TaskConfig
    from bitcomm.learn.config import TrainConfig

MAX_TRAIN_EPISODES = 1_000_000_000
"""A training budget beyond 10^9 episodes would run for years on a CPU."""
MAX_BATCH = 65_536
"""Episodes played side by side (`--envs`, `--num-envs`, `--batch-episodes`); memory is checked too."""
MAX_SAMPLES = 10_000_000
"""`analyze --samples`: 10^7 deliveries is minutes of play and a few hundred MB."""
MAX_REPEATS = 10_000
"""Repetitions of a measurement (`--repeats`, `--batches`, `--fit-*`, `--seeds`): beyond this, days."""
MAX_FRAMES = 1000
"""`render` draws one frame per step of an episode truncated at `--max-steps`: at most 1,000 frames."""
MAX_FPS = 100.0
"""A GIF frame lasts a whole number of 10 ms ticks: more than 100 frames per second cannot be shown."""
MIN_FPS = 0.01
"""And at most 65,535 ticks (655 s), a 16-bit count: 100 s a frame is the slowest `render --fps` makes."""
MAX_SECONDS = 7 * 24 * 3600.0
"""Timeouts in seconds: a week at most."""
MAX_DEADLINE_MS = 60_000.0
"""`deploy --deadline-ms`: a step waits at most a minute for its messages."""
EVAL_BATCH = 4096
"""Episodes evaluation plays side by side (`bitcomm.policies.evaluation.EVAL_CHUNK`, held equal by a test)."""


def _range(least: float, most: float, strict: bool = False) -> str:
    low = f"> {least:g}" if strict else f">= {least:g}"
    return low if math.isinf(most) else f"{'in (' if strict else 'in ['}{least:g}, {most:g}]"


def integer(least: int, most: int, why: str = "") -> Callable[[str], int]:
    """An argparse type: a whole number in [least, most]; `why` says what the cap protects."""

    def parse(text: str) -> int:
        allowed = f"must be an integer in [{least}, {most}]{f' ({why})' if why else ''}"
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid value {text!r}: {allowed}") from None
        if not least <= value <= most:
            raise argparse.ArgumentTypeError(f"invalid value {text!r}: {allowed}")
        return value

    parse.__name__ = "integer"
    return parse


def number(least: float, most: float = math.inf, strict: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number >= least (> with `strict`) and <= most; NaN and inf never are."""

    def parse(text: str) -> float:
        allowed = f"must be a finite number {_range(least, most, strict)}"
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid value {text!r}: {allowed}") from None
        low_ok = value > least if strict else value >= least
        if not (math.isfinite(value) and low_ok and value <= most):
            raise argparse.ArgumentTypeError(f"invalid value {text!r}: {allowed}")
        return value

    parse.__name__ = "number"
    return parse


SEED = integer(0, MAX_SEED)
EVAL_EPISODES = integer(1, MAX_EVAL_EPISODES, "about 170 MB and hours of play")


def _writable(folder: Path) -> bool:
    """Writable by this user, and not marked read-only (no write bit) even for root, who os.access ignores."""
    return os.access(folder, os.W_OK | os.X_OK) and bool(folder.stat().st_mode & 0o222)


def folder_problem(path: Path) -> str | None:
    """Why files cannot be written in folder `path` (made with its parents if missing), or None."""
    if path.exists() and not path.is_dir():
        return "is a file, not a folder"
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        return f"{str(probe)!r} is a file, so no folder can be made in it"
    if not _writable(probe):
        return f"folder {str(probe)!r} is read-only"
    return None


def _user_path(text: str) -> Path:
    """`text` as a path, a leading `~` the home folder: the shell leaves `--out=~/runs` as typed (it expands a
    `~` only at the start of a word), and a folder named `~` made in the working directory is one a later
    `rm -rf ~` would mistake for home."""
    return Path(text).expanduser()


def out_dir(text: str) -> Path:
    """An argparse type: a folder to write into (made if missing), refused if it is a file or read-only."""
    path = _user_path(text)
    problem = "must not be empty" if not text.strip() else folder_problem(path)
    if problem:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: {problem}")
    return path


def out_file(text: str) -> Path:
    """An argparse type: a file to write (its folder made if missing), refused if a folder, a device or read-only."""
    path = _user_path(text)
    problem = None
    if not text.strip():
        problem = "must not be empty"
    elif path.is_dir():
        problem = "is a folder; give a file name"
    elif path.exists() and not path.is_file():  # written by renaming a new file over it: a device would be gone
        problem = "is not a regular file (a device, pipe or socket); give a file name"
    elif path.exists() and not (path.stat().st_mode & 0o222 and os.access(path, os.W_OK)):
        problem = "is a read-only file"
    elif path.parent.exists() and not path.parent.is_dir():  # folder_problem's "is a file" would read as `path`'s
        problem = f"{str(path.parent)!r} is a file, not a folder, so nothing can be written in it"
    else:
        problem = folder_problem(path.parent)
    if problem:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: {problem}")
    return path


def gif_file(text: str) -> Path:
    """An argparse type: `out_file` named `*.gif`, the only format the animation is written in."""
    path = out_file(text)
    if path.suffix.lower() != ".gif":
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: a GIF file name, ending in .gif")
    return path


def play_bytes(task: TaskConfig, episodes: int, steps: int = 1, onehot: bool = False) -> int:
    """Memory of `episodes` played side by side, `steps` of them kept: the uint8 observation planes and
    state (4n S^2), messages in flight (delay n K) and the float32 copies the networks read (x4, twice).
    `onehot`: a policy with one-hot messages also holds, at each acting step, float32 tables of 2^K per
    agent: its logits, their softmax and cumulative sum, and one per slot it hears (what an evaluation of
    4,096 episodes at 18 bits ran out of memory on: 34 GB)."""
    env, ch = task.env, task.channel
    per_step = 4 * env.n_agents * env.cells * 9
    in_flight = ch.delay * env.n_agents * ch.bits * task.slots
    acting = acting_bytes(env.n_agents, ch.bits, task.slots) if onehot else 0
    return episodes * (steps * per_step + in_flight + acting)


def onehot_bytes(cfg: TrainConfig) -> int:
    """Parameters 2^K wide under one-hot messages, in float32 with their gradient and two Adam moments (x16
    bytes): the policy's message output (over the layer it reads) and its input of heard messages (with the
    message map's cells where it has one), and the standard estimator's critic's input of heard messages."""
    model, task = cfg.model, cfg.training_task
    reads = model.sender_hidden if model.message_reads == "observed" else model.hidden
    heard = task.slots * model.message_hidden * (2 if cfg.estimator == "standard" else 1)
    maps = task.env.cells if model.message_map else 0
    return task.channel.messages * (reads + heard + maps) * 16


def network_bytes(cfg: TrainConfig) -> int:
    """A bound on the policy's and both critics' parameters (float32, with gradient and Adam: x16): the
    fully connected layers over the widest convolution output (stride ignored, so an overestimate)."""
    model, task = cfg.model, cfg.task
    wide = max(model.conv_channels, default=1) * task.env.cells + model.message_hidden
    sender = model.sender_hidden * (task.env.cells + model.sender_hidden) if model.message_reads == "observed" else 0
    return 3 * 16 * (model.hidden * (wide + model.hidden) + model.message_hidden * 4 * task.env.n_agents * 64 + sender)


def check_memory(flag: str, value: object, need: int, what: str, hint: str = "") -> None:
    """One error line, with the estimate, when `need` bytes exceed the memory available now (`hint`: what to
    give instead, after it)."""
    have = available_bytes()
    if need > have:
        estimate = f"about {need / BYTES_PER_GB:.1f} GB needed, {have / BYTES_PER_GB:.1f} GB available"
        raise bad_value(flag, value, f"{what}: {estimate}{f'; {hint}' if hint else ''}")


def check_play(
    task: TaskConfig,
    flag: str,
    value: object,
    episodes: int,
    steps: int = 1,
    onehot: bool = False,
    beside: int = 0,
    held_by: str = "",
) -> None:
    """`check_memory` for `episodes` played side by side on `task` (`onehot`: by a policy with one-hot messages),
    with `beside` bytes held while they play (`held_by` says by what)."""
    what = f"{episodes} episodes side by side on this task"
    if onehot:
        what += f" with one-hot messages over 2^{task.channel.bits} words"
    if held_by:
        what += f", beside {held_by}"
    check_memory(flag, value, beside + play_bytes(task, episodes, steps, onehot), what)


def check_eval(task: TaskConfig, episodes: int, onehot: bool = False, flag: str = "episodes") -> None:
    """`check_play` for an evaluation of `episodes` (played `EVAL_BATCH` at a time), asked for by `flag`."""
    check_play(task, flag, episodes, min(episodes, EVAL_BATCH), onehot=onehot)


def check_train(cfg: TrainConfig, processes: int = 1) -> None:
    """Memory of `processes` training runs at once: rollout buffers, and with one-hot messages the parameters
    2^K wide (which is what 24 bits of one-hot messages ran out of: 64 GB) and the tables a batch acts on.
    Measured peaks above a 4-bit run's (10x10, 128 episodes a batch, 3 batches): 124 / 462 / 1,809 MiB at 14 /
    16 / 18 bits (547 at 16 with the standard estimator) against 112 / 448 / 1,792 (512) counted. A run that
    evaluates held-out episodes (`held_out_every`) plays them between batches, `EVAL_BATCH` at a time, beside
    the parameters and a float32 copy of the policy (`bitcomm.learn.held_out`): checked on its own."""
    task = cfg.training_task
    for name, most in (("workers", MAX_JOBS), ("epochs", MAX_REPEATS)):
        if getattr(cfg, name) > most:
            raise bad_value(name.replace("_", "-"), getattr(cfg, name), f"must be an integer in [1, {most}]")
    workers = cfg.workers if cfg.mode == "a3c" or cfg.backend == "ray" else 1
    learners = processes * workers
    at_once = f"{processes} run(s) at once" + (f", {workers} workers each" if workers > 1 else "")  # what is counted
    wider = max(("hidden", "message_hidden", "sender_hidden"), key=lambda name: getattr(cfg.model, name))
    flag, value, what, hint = wider.replace("_", "-"), getattr(cfg.model, wider), f"the networks ({at_once})", ""
    size, read = cfg.task.env.size, max(cfg.model.conv_channels, default=1) * cfg.task.env.cells
    if read > value:  # the first layers' input, the grid's cells, outweighs their width: the size is what to name
        what = f"the networks ({flag} {value}; {at_once}), whose first layers read every cell of the {size}x{size} grid"
        flag, value, hint = "size", size, "give a smaller grid"
    check_memory(flag, value, learners * network_bytes(cfg), what, hint)
    batch = cfg.num_envs * workers * processes
    rollouts = play_bytes(task, batch, task.env.max_steps)
    wide = onehot = 0
    if cfg.model.messages == "onehot":
        wide = learners * onehot_bytes(cfg)
        onehot = wide + batch * acting_bytes(task.env.n_agents, task.channel.bits, task.slots)
    if onehot > rollouts:
        what = f"one-hot messages over 2^{task.channel.bits} words ({at_once})"
        check_memory("bits", task.channel.bits, onehot + rollouts, what)
    else:
        what = f"{batch} episodes of {task.env.max_steps} steps on a {task.env.size}x{task.env.size} grid ({at_once})"
        check_memory("num-envs", cfg.num_envs, onehot + rollouts, what)
    if cfg.held_out_every:
        held = processes * min(cfg.held_out_episodes, EVAL_BATCH)
        copy = wide // 4  # the policy's, without gradient or Adam moments (the standard critic's input too: at most)
        by = f"the 2^{task.channel.bits}-wide parameters and a copy of the policy ({at_once})" if wide else ""
        check_play(
            cfg.task,
            "held-out-episodes",
            cfg.held_out_episodes,
            held,
            onehot=wide > 0,
            beside=wide + copy,
            held_by=by,
        )


THREADS_HELP = "torch threads (default: the cores not busy by the load average, or OMP_NUM_THREADS when set)"


def add_threads_flag(p: argparse.ArgumentParser, more: str = "") -> None:
    """`--threads`, for every command whose time is torch's."""
    p.add_argument("--threads", type=integer(1, MAX_JOBS), default=None, help=THREADS_HELP + more)


OMP_THREADS = "OMP_NUM_THREADS"
_OMP_COUNT = re.compile(r"\s*\+?[0-9]+\s*")


def check_omp_threads() -> None:
    """Refuse an OMP_NUM_THREADS that OpenMP would not read (a positive count, or OpenMP's list of one per
    nesting level, `4,2`), before torch loads: its OpenMP runtime would print its own warning line and pick
    the threads itself. An empty one is unset (as `default_threads` reads it), and removed so OpenMP is quiet."""
    text = os.environ.get(OMP_THREADS)
    if text is not None and not text.strip():
        del os.environ[OMP_THREADS]
    elif text is not None and not all(_OMP_COUNT.fullmatch(n) and int(n) > 0 for n in text.split(",")):
        allowed = "must be a positive integer (torch's threads); unset, --threads or the idle cores choose them"
        raise bad_value(OMP_THREADS, text, allowed)


def default_threads() -> int | None:
    """The cores not busy now (by the 1-minute load average), at least 1; None when OMP_NUM_THREADS is set.

    Measured (issue 20): with one other busy core, torch's default of 2 threads trained
    2.9x slower (44.7 s per 1,280 episodes) while 1 thread lost far less (21.1 s); `bitcomm eval` of
    200 32x32 episodes beside two busy cores took 11.9 s on 2 threads against 3.7 s on 1 (session 18).
    """
    if os.environ.get(OMP_THREADS):
        return None
    cores = os.cpu_count() or 1
    return max(1, cores - round(os.getloadavg()[0]))


def use_threads(args: argparse.Namespace) -> int | None:
    """Set torch's threads from `--threads` or `default_threads()`; returns the count (None: OMP_NUM_THREADS)."""
    threads = args.threads or default_threads()
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    return threads


def check_episodes(episodes: int) -> int:
    """Evaluation episodes given other than on the command line (a library call, a resumed config)."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or not 1 <= episodes <= MAX_EVAL_EPISODES:
        raise bad_value("episodes", episodes, f"must be an integer in [1, {MAX_EVAL_EPISODES}]")
    return episodes


class HelpFormatter(argparse.HelpFormatter):
    """Shows every flag's default: help that names no default gets "(default: X)" appended. A switch (default
    False) and a flag without one (None) show none; 0 and 0.0 are defaults (`in (None, False)` took them for False:
    --flip-prob, --drop-prob, --act-fail-prob and --act-delay showed none)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        none = any(action.default is value for value in (None, False, argparse.SUPPRESS))
        if "default" in text.lower() or none or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)".strip()
