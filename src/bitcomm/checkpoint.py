"""Checkpoints of a training run, in `<run>/checkpoints/`.

Each checkpoint is two files with the same stem, `ckpt_<episodes:09d>`:

- `.safetensors`: the weights, keys prefixed `policy.` and `critic.`, and in the safetensors metadata
  the training config (JSON), the episodes and batches played, and the format version. This file
  alone is enough to act (`bitcomm.Controller`).
- `.state.pt`: what resuming needs besides the weights (optimizer states, the sampling generator,
  counters, the recent episode lengths of the rolling mean); read with `torch.load(weights_only=True)`.

Every file is written to a temporary name in the same folder and renamed into place (atomic on
POSIX), and `latest.json` is replaced only once both files of a checkpoint exist, so a run killed at
any moment leaves a readable latest checkpoint. Checkpoints are kept, not rotated.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from bitcomm.errors import ConfigError

FORMAT = "bitcomm-checkpoint"
VERSION = 1
LATEST = "latest.json"
CHECKPOINTS = "checkpoints"


def _bad(path: Path | str, why: str) -> ConfigError:
    return ConfigError(f"invalid checkpoint={str(path)!r}: {why}")


def _atomic(path: Path, write: Any) -> None:
    """`write(tmp_path)` then rename over `path`."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def save_checkpoint(
    run: Path,
    config: dict[str, Any],
    weights: dict[str, dict[str, torch.Tensor]],
    episodes: int,
    batches: int,
    state: dict[str, Any],
) -> Path:
    """Write `ckpt_<episodes>.safetensors` + `.state.pt` and point `latest.json` at them."""
    from safetensors.torch import save_file

    folder = run / CHECKPOINTS
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"ckpt_{episodes:09d}"
    tensors = {
        f"{prefix}.{k}": v.detach().contiguous().clone() for prefix, sd in weights.items() for k, v in sd.items()
    }
    meta = {
        "format": FORMAT,
        "version": str(VERSION),
        "config": json.dumps(config),
        "episodes": str(episodes),
        "batches": str(batches),
    }
    weights_path = folder / f"{stem}.safetensors"
    state_path = folder / f"{stem}.state.pt"
    _atomic(weights_path, lambda p: save_file(tensors, str(p), metadata=meta))
    _atomic(state_path, lambda p: torch.save({**state, "episodes": episodes, "batches": batches}, p))
    pointer = {"checkpoint": weights_path.name, "state": state_path.name, "episodes": episodes, "batches": batches}
    _atomic(folder / LATEST, lambda p: p.write_text(json.dumps(pointer) + "\n"))
    return weights_path


def resolve(path: Path | str) -> Path:
    """A run folder, its `checkpoints/` folder or a `.safetensors` file -> the checkpoint file."""
    p = Path(path)
    if p.is_dir():
        folder = p / CHECKPOINTS if (p / CHECKPOINTS).is_dir() else p
        latest = folder / LATEST
        if not latest.is_file():
            raise _bad(path, f"no {CHECKPOINTS}/{LATEST} in this folder (not a bitcomm run)")
        try:
            name = json.loads(latest.read_text())["checkpoint"]
        except (ValueError, KeyError, TypeError) as err:
            raise _bad(path, f"unreadable {LATEST} ({err})") from None
        p = folder / name
    if not p.is_file():
        raise _bad(path, "no such file or run folder")
    return p


def checkpoints(run: Path | str) -> list[tuple[int, Path]]:
    """Every checkpoint a run kept, as `(episodes, weights file)` in training order (checkpoints are
    not rotated, so these are the run's stages). Files of an unfinished write (no `.state.pt`) are left out."""
    p = Path(run)
    folder = p / CHECKPOINTS if (p / CHECKPOINTS).is_dir() else p
    if not (folder / LATEST).is_file():
        raise _bad(run, f"no {CHECKPOINTS}/{LATEST} in this folder (not a bitcomm run)")
    found = []
    for file in folder.glob("ckpt_*.safetensors"):
        stem = file.name.removesuffix(".safetensors")
        if stem[5:].isdigit() and file.with_name(f"{stem}.state.pt").is_file():
            found.append((int(stem[5:]), file))
    return sorted(found)


def load_weights(path: Path | str) -> tuple[dict[str, dict[str, torch.Tensor]], dict[str, Any]]:
    """Weights by prefix (`policy`, `critic`) and metadata (config as a dict, episodes, batches)."""
    from safetensors import safe_open

    file = resolve(path)
    try:
        with safe_open(str(file), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as err:  # safetensors raises its own error types for damaged files
        raise _bad(path, f"not a bitcomm checkpoint ({type(err).__name__}: {err})") from None
    if meta.get("format") != FORMAT:
        raise _bad(path, "not a bitcomm checkpoint (no bitcomm metadata)")
    if int(meta.get("version", -1)) > VERSION:
        raise _bad(path, f"format version {meta['version']} is newer than this bitcomm reads ({VERSION})")
    weights: dict[str, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        prefix, _, name = key.partition(".")
        weights.setdefault(prefix, {})[name] = value
    try:
        info = {
            "config": json.loads(meta["config"]),
            "episodes": int(meta["episodes"]),
            "batches": int(meta["batches"]),
        }
    except (KeyError, ValueError) as err:
        raise _bad(path, f"not a bitcomm checkpoint (bad metadata: {err})") from None
    return weights, {**info, "path": str(file)}


def load_state(weights_file: Path) -> dict[str, Any]:
    """The resume state stored next to a checkpoint's weights."""
    state_path = weights_file.with_name(weights_file.name.replace(".safetensors", ".state.pt"))
    if not state_path.is_file():
        raise _bad(weights_file, f"its resume state {state_path.name} is missing")
    try:
        state: dict[str, Any] = torch.load(state_path, weights_only=True)
    except Exception as err:
        raise _bad(state_path, f"not a bitcomm resume state ({type(err).__name__}: {err})") from None
    return state
