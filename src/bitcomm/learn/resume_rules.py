"""What a resume may change of the run it continues: the budget, where it runs and how often it saves, none of which
changes what it learns. `bitcomm train --resume` checks the flags typed with it (`commands.backend_flags`), and
`train(cfg, out, resume=True)` the config given from Python (`learn.run_folder.prepare`). Torch-free, as every parser.
"""

from __future__ import annotations

import json
from typing import Any

SAVING = ("checkpoint_seconds", "keep_checkpoints")
"""The options that say how often a run saves: a resume applies them as given now."""
RESUME_MAY_CHANGE = frozenset({"episodes", "backend", "workers", "staleness", "env_workers", *SAVING})
"""The options a resume takes as given now: the budget, where it runs and how often it saves."""


def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"model": {"hidden": 128}} -> {"model.hidden": 128}, so a difference names the option."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def changed_on_resume(recorded: dict[str, Any], given: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """`(option, given, recorded)` for each option of a config `given` for a resume (`to_dict()`) that differs from
    the one the run `recorded` (its checkpoint's, as JSON) and that a resume may not change; an option the record
    lacks (a run from before it existed) is left out."""
    was = flat(recorded)
    now = flat(json.loads(json.dumps(given)))  # as the record gives it back: a tuple as a list
    return [
        (name, value, was[name])
        for name, value in now.items()
        if name in was and name.split(".")[0] not in RESUME_MAY_CHANGE and value != was[name]
    ]
