"""`bitcomm export RUN --onnx FILE`: the policy network as ONNX, for robots without PyTorch.

RUN is a run folder or a checkpoint file, as for `bitcomm eval`. FILE gets the graph (inputs `planes`,
`received`; outputs `move_logits`, `message_logits`; dynamic batch axis) and `FILE.json` its card;
`bitcomm deploy --onnx FILE` and `bitcomm.policies.onnx_policy.OnnxController` run it
(see `bitcomm.policies.onnx_export`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bitcomm.commands.flags import out_file
from bitcomm.errors import bad_value
from bitcomm.stop_signals import sigterm_interrupts


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export a trained policy network to ONNX (run folder or checkpoint file)")
    p.add_argument("run_path", metavar="RUN_OR_CHECKPOINT", help="run folder or .safetensors file")
    p.add_argument(
        "--onnx", type=out_file, required=True, metavar="FILE", help="ONNX file to write (its card goes to FILE.json)"
    )
    p.set_defaults(run=run)


def _check_output(path: Path) -> None:
    """Refuse, before any work, an output that cannot be written (a folder where the graph or its card goes), or that
    would replace a file of a training run (a checkpoint, `latest.json`, config.json: `--onnx RUN/checkpoints/latest`
    writes its card to latest.json)."""
    from bitcomm.checkpoint import LATEST, is_run_folder
    from bitcomm.learn.run_folder import RUN_FILES
    from bitcomm.policies.onnx_policy import sidecar_path

    if path.is_dir():
        raise bad_value("onnx", str(path), "is a folder; give a file name such as policy.onnx")
    if sidecar_path(path).is_dir():  # found only once the graph was written, and named as if the graph were at fault
        raise bad_value("onnx", str(path), f"its card would go to {str(sidecar_path(path))!r}, which is a folder")
    if (path.parent / LATEST).is_file():
        raise bad_value("onnx", str(path), "is in a run's checkpoints folder, where it could replace the run's files")
    for target in (path, sidecar_path(path)):
        if target.name in RUN_FILES and is_run_folder(target.parent):
            raise bad_value("onnx", str(path), f"it or its card would replace the run's {target.name}")


@sigterm_interrupts()  # from its first line: a stop leaves no half-written file, nor its temporary
def run(args: argparse.Namespace) -> int:
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.onnx_export import export_onnx
    from bitcomm.policies.onnx_policy import require, sidecar_path

    out = Path(args.onnx)
    _check_output(out)
    require("onnx")
    controller = Controller.load(args.run_path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)  # as `render --out` and every other output flag do
        card = export_onnx(controller, out)
    except OSError as err:
        raise bad_value("onnx", str(out), f"cannot be written ({err.strerror or err})") from None
    print(
        f"wrote {out} and {sidecar_path(out)}: {card['size']}x{card['size']} grid, {card['bits']} bits, "
        f"{card['slots']} slot(s), {card['messages']} messages, from {card['checkpoint']}"
    )
    return 0
