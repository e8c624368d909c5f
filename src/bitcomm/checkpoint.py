"""Checkpoints of a training run, in `<run>/checkpoints/`.

Each checkpoint is two files with the same stem, `ckpt_<episodes:09d>`:

- `.safetensors`: the weights, keys prefixed `policy.` and `critic.`, and in the safetensors metadata
  the training config (JSON), the episodes and batches played, the rolling mean episode length, the
  format version, the sha256 of the state file and `sha256`, a checksum of everything else in the file
  (metadata and tensors), verified on every load. This file alone is enough to act (`bitcomm.Controller`).
- `.state.pt`: what resuming needs besides the weights (optimizer states, the sampling generator,
  counters, the recent episode lengths of the rolling mean); read with `torch.load(weights_only=True)`
  after its checksum is compared with the one its weights file records.

Every file is written to a temporary name in the same folder and renamed into place (atomic on
POSIX): the state first, then the weights, then `latest.json`, which is replaced only once both files
of a checkpoint exist, so a run killed at any moment leaves a readable latest checkpoint. What a kill
leaves besides (temporary files, a state without its weights, files newer than `latest.json`) is
removed by `clean` when a run starts or resumes. Nothing non-finite is ever written (`Diverged`).
`prune` keeps the last N checkpoints and the best one (the lowest `rank`: the rolling mean episode length on
the grid, minus the rolling mean team return on a wrapped env, whose episodes may all have one length, or the
held-out evaluation's mean episode length where a run evaluates, `TrainConfig.held_out_every`), and `best.json`
names the best, written before the prune that may remove the one it named: so
`bitcomm eval RUN/checkpoints/best.json` (any command that reads a run) reads the best checkpoint.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pickle
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import torch

from bitcomm.errors import ConfigError, bad_value, one_line
from bitcomm.files import write_atomic

FORMAT = "bitcomm-checkpoint"
VERSION = 2
"""1: no checksums (still read, unverified); 2: `sha256`, `state_sha256` and `rolling_length`."""
LATEST = "latest.json"
BEST = "best.json"
POINTERS = (LATEST, BEST)
"""The files of a checkpoints folder that name one of its checkpoints."""
CHECKPOINTS = "checkpoints"
T = TypeVar("T")
NAME = re.compile(r"ckpt_(\d{9})\.(safetensors|state\.pt)")
"""A checkpoint file's name; `latest.json` may name nothing else (so it cannot leave the folder)."""


class Diverged(ConfigError):
    """Training produced a NaN or infinite weight or optimizer value; it was not saved."""


def _bad(path: Path | str, why: str) -> ConfigError:
    return ConfigError(f"invalid checkpoint={str(path)!r}: {why}")


def _atomic(path: Path, write: Any) -> str:
    """`write(tmp_path)` then rename over `path` (`bitcomm.files.write_atomic`); returns the sha256 of what was
    written."""
    digest: list[str] = []

    def write_and_hash(tmp: Path) -> None:
        write(tmp)
        digest.append(file_sha256(tmp))

    write_atomic(path, write_and_hash)
    return digest[0]


def _torch_save(obj: Any, path: Path) -> None:
    """`torch.save`, but a write that fails raises the `OSError` that failed it: torch reports a full disk as a
    RuntimeError naming a position in its zip writer, which says nothing of the disk."""
    failed: list[OSError] = []

    class Recorder:
        def __init__(self, file: Any) -> None:
            self.file = file

        def write(self, data: Any) -> int:
            try:
                return int(self.file.write(data))
            except OSError as err:
                failed.append(err)
                raise

        def flush(self) -> None:
            self.file.flush()

    with path.open("wb") as file:
        try:
            torch.save(obj, Recorder(file))  # type: ignore[arg-type]
        except RuntimeError:
            if failed:
                raise failed[0] from None
            raise


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def content_sha256(tensors: dict[str, torch.Tensor], meta: dict[str, str]) -> str:
    """A checksum of a weights file's metadata (but its own `sha256`) and tensors: names, dtypes, shapes, bytes."""
    h = hashlib.sha256(json.dumps({k: v for k, v in meta.items() if k != "sha256"}, sort_keys=True).encode())
    for name in sorted(tensors):
        t = tensors[name].detach().contiguous()
        h.update(f"\n{name}|{t.dtype}|{tuple(t.shape)}\n".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------- NaN guard
def _tensors(obj: Any, name: str) -> Iterator[tuple[str, torch.Tensor]]:
    """Every tensor inside nested dicts and lists, with a dotted name."""
    if isinstance(obj, torch.Tensor):
        yield name, obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _tensors(v, f"{name}.{k}")
    elif isinstance(obj, (list, tuple)):
        for k, v in enumerate(obj):
            yield from _tensors(v, f"{name}.{k}")


def first_nonfinite(**groups: Any) -> str | None:
    """The name of the first floating-point tensor holding a NaN or inf, or None."""
    for group, obj in groups.items():
        for name, t in _tensors(obj, group):
            if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                return name
    return None


def latest_name(run: Path | str) -> str | None:
    """The file name of the checkpoint a run's `latest.json` names (what `--resume` goes on from), or None."""
    try:
        return str(read_latest(Path(run) / CHECKPOINTS)["checkpoint"])
    except ConfigError:
        return None


def refuse_nonfinite(run: Path, episodes: int, **groups: Any) -> None:
    """Stop the run with one line, writing nothing, if a weight or optimizer value is NaN or inf."""
    name = first_nonfinite(**groups)
    if name is None:
        return
    latest = latest_name(run)
    kept = f"the latest checkpoint stays {latest}" if latest else "no checkpoint was written"
    raise Diverged(
        f"training diverged after {episodes} episodes: {name} holds NaN or inf; stopped without saving it, "
        f"{kept} (a smaller --lr may help)"
    )


# ---------------------------------------------------------------------------------------------- write
def save_checkpoint(
    run: Path,
    config: dict[str, Any],
    weights: dict[str, dict[str, torch.Tensor]],
    episodes: int,
    batches: int,
    state: dict[str, Any],
    rolling_length: float | None = None,
    keep: int | None = None,
    rank: float | None = None,
) -> Path:
    """Write `ckpt_<episodes>.state.pt` + `.safetensors` and point `latest.json` at them; then, with
    `keep`, `prune` to the last `keep` and the best (lowest `rank`, by default `rolling_length`). Nothing is
    written if a value is not finite."""
    from safetensors.torch import save

    refuse_nonfinite(run, episodes, **weights, state=state)
    folder = run / CHECKPOINTS
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"ckpt_{episodes:09d}"
    tensors = {
        f"{prefix}.{k}": v.detach().contiguous().clone() for prefix, sd in weights.items() for k, v in sd.items()
    }
    weights_path = folder / f"{stem}.safetensors"
    state_path = folder / f"{stem}.state.pt"
    state_sha = _atomic(state_path, lambda p: _torch_save({**state, "episodes": episodes, "batches": batches}, p))
    meta = {
        "format": FORMAT,
        "version": str(VERSION),
        "config": json.dumps(config),
        "episodes": str(episodes),
        "batches": str(batches),
        "rolling_length": repr(float("nan") if rolling_length is None else float(rolling_length)),
        "rank": repr(float("nan") if rank is None else float(rank)),
        "state_sha256": state_sha,
    }
    meta["sha256"] = content_sha256(tensors, meta)
    # the bytes written by Python, not by `save_file`, which makes its files owner-only whatever the umask: the
    # weights are read as the run's other files are (a teammate's `bitcomm eval` on a shared run folder)
    _atomic(weights_path, lambda p: p.write_bytes(save(tensors, metadata=meta)))
    _point(folder / LATEST, episodes, batches)
    best = _best(checkpoints(folder))
    _point(folder / BEST, best, _batches(folder, best, episodes, batches))
    if keep is not None:
        prune(folder, keep, best)
    return weights_path


def _point(pointer: Path, episodes: int, batches: int) -> None:
    stem = f"ckpt_{episodes:09d}"
    record = {
        "checkpoint": f"{stem}.safetensors",
        "state": f"{stem}.state.pt",
        "episodes": episodes,
        "batches": batches,
    }
    _atomic(pointer, lambda p: p.write_text(json.dumps(record) + "\n"))


def _batches(folder: Path, episodes: int, latest_episodes: int, latest_batches: int) -> int:
    if episodes == latest_episodes:
        return latest_batches
    try:
        return int(_metadata(folder / f"ckpt_{episodes:09d}.safetensors").get("batches", "0"))
    except (ConfigError, ValueError):
        return 0


# ---------------------------------------------------------------------------------------------- find
def _folder(path: Path | str) -> Path:
    p = Path(path)
    return p / CHECKPOINTS if (p / CHECKPOINTS).is_dir() else p


def read_latest(folder: Path, which: str = LATEST) -> dict[str, Any]:
    """`latest.json` (or another pointer, `POINTERS`) of a checkpoints folder, checked: it names a checkpoint
    file of this very folder."""
    latest = folder / which
    try:
        pointer = json.loads(latest.read_text())
    except FileNotFoundError:
        raise _bad(latest, "no such file (not a bitcomm run)") from None
    except (OSError, ValueError) as err:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise _bad(latest, f"unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(pointer, dict):
        raise _bad(latest, f"not a JSON object ({type(pointer).__name__})")
    name = pointer.get("checkpoint")
    match = NAME.fullmatch(name) if isinstance(name, str) else None
    if match is None or match.group(2) != "safetensors":
        raise _bad(latest, f"'checkpoint' must name a ckpt_<episodes>.safetensors file of its folder, not {name!r}")
    episodes = pointer.get("episodes", int(match.group(1)))
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes != int(match.group(1)):
        raise _bad(latest, f"'episodes' must be {int(match.group(1))} (the checkpoint it names), not {episodes!r}")
    file = folder / match.group(0)
    if file.is_symlink() and file.resolve().parent != folder.resolve():
        raise _bad(latest, f"{name} links outside the run folder")
    return dict(pointer)


def is_run_folder(out: Path) -> bool:
    """Whether `out`'s config.json is a run's (`write_config`'s record: a config with its seed and versions)."""
    try:
        record = json.loads((out / "config.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and "seed" in record and "versions" in record


def _no_latest(path: Path | str) -> ConfigError:
    """Why a folder (or a missing path) has no checkpoint to read: a run folder that has none yet is a run, stopped
    before its first checkpoint or still playing toward it, not a folder of something else."""
    p = Path(path)
    if not p.exists():
        return _bad(path, "no such file or run folder")
    if is_run_folder(p.parent if p.name == CHECKPOINTS else p):
        return _bad(
            path,
            "a run with no checkpoint yet: it stopped before its first one, or is still playing toward it (one is "
            "written every --checkpoint-seconds); wait for that one, or train the run again",
        )
    return _bad(path, f"no {CHECKPOINTS}/{LATEST} in this folder (not a bitcomm run)")


def _not_a_file(path: Path) -> str:
    return "is a folder, not a checkpoint file" if path.is_dir() else "is missing"


def resolve(path: Path | str) -> Path:
    """A run folder, its `checkpoints/` folder, a pointer in it (`latest.json`, `best.json`) or a `.safetensors`
    file -> the checkpoint file."""
    if not isinstance(path, (str, os.PathLike)):  # `Controller.load(None)` was pathlib's "expected str, bytes or ..."
        raise bad_value("path", path, "must be a run folder or a checkpoint file, as a str or a Path")
    p = Path(path)
    if p.name in POINTERS and p.is_file():
        named = p.parent / read_latest(p.parent, p.name)["checkpoint"]
        if not named.is_file():
            raise _bad(p, f"names {named.name}, which {_not_a_file(named)}")
        return named
    if p.is_dir():
        folder = _folder(p)
        if not (folder / LATEST).is_file():
            raise _no_latest(path)
        p = folder / read_latest(folder)["checkpoint"]
        if not p.is_file():
            raise _bad(folder / LATEST, f"names {p.name}, which {_not_a_file(p)}")
    if not p.is_file():
        raise _bad(path, "no such file or run folder")
    return p


def _stems(folder: Path) -> dict[int, set[str]]:
    """Episodes -> the kinds of checkpoint file present (`safetensors`, `state.pt`)."""
    found: dict[int, set[str]] = {}
    for file in folder.glob("ckpt_*"):
        match = NAME.fullmatch(file.name)
        if match:
            found.setdefault(int(match.group(1)), set()).add(match.group(2))
    return found


def checkpoints(run: Path | str) -> list[tuple[int, Path]]:
    """Every checkpoint a run kept (see `prune`), as `(episodes, weights file)` in training order.
    Files of an unfinished write (no `.state.pt`) are left out."""
    folder = _folder(run)
    if not (folder / LATEST).is_file():
        raise _no_latest(run)
    return complete(folder)


def complete(folder: Path) -> list[tuple[int, Path]]:
    """`checkpoints` of a checkpoints folder whether or not it has its `latest.json`."""
    return [
        (e, folder / f"ckpt_{e:09d}.safetensors")
        for e, kinds in sorted(_stems(folder).items())
        if kinds == {"safetensors", "state.pt"}
    ]


# ---------------------------------------------------------------------------------------------- tidy
def _remove(folder: Path, episodes: int) -> None:
    """Both files of a checkpoint, the weights first: a half-removed one is never listed."""
    for suffix in ("safetensors", "state.pt"):
        (folder / f"ckpt_{episodes:09d}.{suffix}").unlink(missing_ok=True)


def clean(run: Path) -> list[str]:
    """Remove what a killed writer left in a run folder (call it holding the run's lock): temporary
    files, checkpoint files without their pair, and checkpoints newer than `latest.json` (never committed;
    all of them when there is no `latest.json`). The files `latest.json` names are never removed (a
    missing state is then refused on resume with one line). Returns the names removed."""
    removed = []
    folder = run / CHECKPOINTS
    for where in (run, folder):
        for tmp in where.glob(".*.tmp*"):
            if tmp.is_file():
                tmp.unlink()
                removed.append(tmp.name)
    if not folder.is_dir():
        return removed
    committed = read_latest(folder)["episodes"] if (folder / LATEST).is_file() else -1
    for episodes, kinds in _stems(folder).items():
        if episodes != committed and (kinds != {"safetensors", "state.pt"} or episodes > committed):
            _remove(folder, episodes)
            removed += [f"ckpt_{episodes:09d}.{k}" for k in sorted(kinds)]
    return removed


def _recorded(file: Path, key: str) -> float:
    try:
        value = float(_metadata(file).get(key, "inf"))
    except (ConfigError, ValueError):
        return math.inf
    return value if math.isfinite(value) else math.inf


def rolling_length(file: Path) -> float:
    """The rolling mean episode length a checkpoint recorded (inf where it has none)."""
    return _recorded(file, "rolling_length")


def rank(file: Path) -> float:
    """What retention ranks a checkpoint by, lower is better: its recorded `rank` (inf: recorded as unranked,
    a checkpoint written between a run's evaluations), else (none recorded, or checkpoints written before ranks)
    its rolling mean episode length; inf where it has neither."""
    try:
        value = float(_metadata(file).get("rank", "nan"))
    except (ConfigError, ValueError):
        return math.inf
    return value if not math.isnan(value) else rolling_length(file)


def _best(kept: list[tuple[int, Path]]) -> int:
    """The episodes of the best of `kept` (lowest `rank`, the later of equals)."""
    return min(kept, key=lambda ef: (rank(ef[1]), -ef[0]))[0]


def prune(folder: Path, keep: int, best: int | None = None) -> list[int]:
    """Remove every checkpoint but the last `keep` and the best (lowest `rank`, the later of equals, the one
    `best.json` names; `best` if the caller has just found it); `latest.json`'s is always among the last.
    Returns the episodes removed."""
    kept = checkpoints(folder)
    if len(kept) <= keep:
        return []
    if best is None:
        best = _best(kept)
    gone = [e for e, _ in kept[:-keep] if e != best]
    for episodes in gone:
        _remove(folder, episodes)
    return gone


# ---------------------------------------------------------------------------------------------- read
def _metadata(file: Path) -> dict[str, str]:
    from safetensors import safe_open

    try:
        with safe_open(str(file), framework="pt") as f:
            return dict(f.metadata() or {})
    except Exception as err:  # safetensors raises its own error types for damaged files
        raise _bad(file, f"not a bitcomm checkpoint ({type(err).__name__}: {err})") from None


def _version(file: Path, meta: dict[str, str]) -> int:
    if meta.get("format") != FORMAT:
        raise _bad(file, "not a bitcomm checkpoint (no bitcomm metadata)")
    text = meta.get("version", "")
    if not text.isdecimal():  # not isdigit: int() refuses a digit such as "²"
        raise _bad(file, f"metadata version {text!r} is not a whole number")
    if int(text) > VERSION:
        raise _bad(file, f"format version {text} is newer than this bitcomm reads ({VERSION})")
    return int(text)


def load_weights(path: Path | str) -> tuple[dict[str, dict[str, torch.Tensor]], dict[str, Any]]:
    """Weights by prefix (`policy`, `critic`) and metadata (config as a dict, episodes, batches),
    refused with one line if the file's checksum does not match what it holds."""
    return _read_resolved(path, _load_weights_file)


def _load_weights_file(file: Path) -> tuple[dict[str, dict[str, torch.Tensor]], dict[str, Any]]:
    from safetensors import safe_open

    try:
        with safe_open(str(file), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as err:  # safetensors raises its own error types for damaged files
        raise _bad(file, f"not a bitcomm checkpoint ({type(err).__name__}: {err})") from None
    if _version(file, meta) >= 2 and content_sha256(tensors, meta) != meta.get("sha256"):
        raise _bad(file, "checksum mismatch: the file was changed or damaged after it was written")
    weights: dict[str, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        prefix, _, name = key.partition(".")
        weights.setdefault(prefix, {})[name] = value
    config = _config(file, meta)
    try:
        info = {"config": config, "episodes": int(meta["episodes"]), "batches": int(meta["batches"])}
    except (KeyError, ValueError) as err:
        raise _bad(file, f"not a bitcomm checkpoint (bad metadata: {err})") from None
    return weights, {**info, "path": str(file)}


def _config(file: Path, meta: dict[str, str]) -> dict[str, Any]:
    try:
        config = json.loads(meta["config"])
    except (KeyError, ValueError) as err:
        raise _bad(file, f"not a bitcomm checkpoint (bad metadata: {err})") from None
    if not isinstance(config, dict):
        raise _bad(file, "not a bitcomm checkpoint (its config is not a JSON object)")
    return config


def read_config(path: Path | str) -> dict[str, Any]:
    """The config a checkpoint (or a run folder's latest) was trained with, from its metadata alone: what a
    command needs to choose how to load it, without reading (or checking) its tensors twice."""
    return _read_resolved(path, _config_of_file)


def _config_of_file(file: Path) -> dict[str, Any]:
    meta = _metadata(file)
    _version(file, meta)
    return _config(file, meta)


READS = 3
"""How often a reader of a run still training resolves its latest checkpoint again (`_read_resolved`)."""


def _read_resolved(path: Path | str, read: Callable[[Path], T]) -> T:
    """`read(resolve(path))`; where `path` is a run (or a pointer) still training, whose checkpoint was pruned
    between the two (`prune`: the run saved `keep` newer ones meanwhile), `read` the one it names now, rather than
    call the file it named a damaged checkpoint."""
    for _ in range(READS - 1):
        file = resolve(path)
        try:
            return read(file)
        except ConfigError:
            if file.exists() or file == Path(path):
                raise
    return read(resolve(path))


def is_env_config(d: dict[str, Any]) -> bool:
    """A config dict (config.json, checkpoint metadata) of a run on a wrapped env, not on the grid."""
    return isinstance(d.get("env"), str) and "channel" in d and "task" not in d


def load_grid_weights(path: Path | str) -> tuple[dict[str, dict[str, torch.Tensor]], dict[str, Any]]:
    """`load_weights` for the commands that read runs of the grid task alone (analyze, deploy, export, variance):
    a run trained on a wrapped env is one line naming its env, not a missing key of the grid's config."""
    weights, info = load_weights(path)
    if is_env_config(info["config"]):
        raise _bad(
            info["path"],
            f"trained on a wrapped env ({info['config']['env']}); this command reads runs of the grid task "
            "(bitcomm eval and bitcomm render read both; from Python, bitcomm.EnvController acts with it)",
        )
    return weights, info


def load_env_weights(path: Path | str) -> tuple[dict[str, dict[str, torch.Tensor]], dict[str, Any]]:
    """`load_weights` for the readers of runs on a wrapped env (`load_env_policy`, and so `evaluate_env` and
    `bitcomm.EnvController`): a grid run is one line saying what reads it, not a missing key of an env's config."""
    weights, info = load_weights(path)
    if not is_env_config(info["config"]):
        raise _bad(
            info["path"],
            "trained on the grid task, not on a wrapped env; bitcomm.Controller acts with it "
            "(bitcomm eval and bitcomm render read both)",
        )
    return weights, info


WEIGHTS_ONLY_REFUSAL = "Weights only load failed"
"""How torch's `weights_only` load begins its refusal of an object it will not build (a pickle's code)."""
REFUSED_GLOBAL = re.compile(r"GLOBAL ([\w.]+)")
"""The function or class such a refusal names (`GLOBAL posix.system`), in torch's words of any version."""


def _refused_object(err: pickle.UnpicklingError) -> str:
    """An unpickling error on one line. Where `weights_only` refused an object (a crafted file's code), the
    function or class it refused, not torch's paragraphs, which advise loading the file with `weights_only=False`:
    that would run it."""
    text = str(err)
    if not text.startswith(WEIGHTS_ONLY_REFUSAL):
        return one_line(err)
    named = REFUSED_GLOBAL.search(text)
    what = f" ({named.group(1)})" if named else ""
    return f"it holds an object other than tensors and plain values{what}, refused unloaded as it could run code"


def load_state(weights_file: Path) -> dict[str, Any]:
    """The resume state stored next to a checkpoint's weights, checked against the weights' record of it."""
    state_path = weights_file.with_name(weights_file.name.replace(".safetensors", ".state.pt"))
    if not state_path.is_file():
        raise _bad(weights_file, f"its resume state {state_path.name} {_not_a_file(state_path)}")
    meta = _metadata(weights_file)
    if _version(weights_file, meta) >= 2 and file_sha256(state_path) != meta.get("state_sha256"):
        raise _bad(state_path, "checksum mismatch: the file was changed or damaged after it was written")
    try:
        state = torch.load(state_path, weights_only=True)
    except pickle.UnpicklingError as err:
        raise _bad(state_path, f"not a bitcomm resume state ({_refused_object(err)})") from None
    except Exception as err:
        raise _bad(state_path, f"not a bitcomm resume state ({one_line(err)})") from None
    if not isinstance(state, dict):
        raise _bad(state_path, "not a bitcomm resume state (not a dict)")
    return state
