"""Export a trained policy network to ONNX, for robots that run onnxruntime instead of PyTorch.

The graph is `PolicyNet.forward` as `Controller` runs it (coordinate planes and the message head's
reading of the received bits included), with a dynamic batch axis; see `bitcomm.policies.onnx_policy` for its
inputs, outputs and how to sample from them. The card a robot needs (task, head, tensor names and
shapes, bitcomm version, source checkpoint) goes into the model's metadata and into a JSON sidecar.

The exporter is PyTorch's TorchScript-based one (`dynamo=False`): it needs nothing beyond the `onnx`
extra, works on every torch this package accepts, and takes milliseconds; the `torch.export`-based
default would add `onnxscript` and seconds per export for the same graph of convolutions and linears.
"""

from __future__ import annotations

import inspect
import json
import warnings
from pathlib import Path
from typing import Any

import torch

from bitcomm.envs.core import DCOL, DROW, MOVE_NAMES
from bitcomm.files import write_atomic, write_text_atomic
from bitcomm.policies.controller import Controller
from bitcomm.policies.onnx_policy import FORMAT, INPUTS, METADATA_KEY, OUTPUTS, VERSION, require, sidecar_path

OPSET = 17  # onnxruntime >= 1.14 runs it; the graph needs nothing newer


def checkpoint_named(controller: Controller) -> str:
    """The checkpoint the policy was loaded from, as an absolute path (one relative to where export ran traces
    nowhere once the card is on a robot); "" for a controller built in memory."""
    path = controller.info.get("path")
    return str(Path(path).resolve()) if path else ""


def policy_card(controller: Controller) -> dict[str, Any]:
    """What a robot needs to feed the exported graph and read its outputs, and where it came from: enough for a
    runtime without bitcomm (C++, a microcontroller), so who hears whom is written out rather than left to
    `task`'s defaults, and `encoding` says what each tensor holds."""
    import bitcomm

    task, head = controller.task, controller.policy.head
    S, K, slots = task.env.size, task.channel.bits, task.slots
    if head.name == "bitwise":
        message = "bit k is 1 where logit k > 0 (greedy), or with probability sigmoid(logit k)"
    else:
        message = "index argmax (greedy) or drawn from softmax, sent as its K bits, most significant first"
    return {
        "format": FORMAT,
        "version": VERSION,
        "bitcomm_version": bitcomm.__version__,
        "checkpoint": checkpoint_named(controller),
        "episodes_trained": controller.info.get("episodes"),
        "size": S,
        "agents": task.env.n_agents,
        "bits": K,
        "slots": slots,
        "messages": head.name,
        "moves": list(MOVE_NAMES),
        "move_deltas": [[int(r), int(c)] for r, c in zip(DROW, DCOL, strict=True)],
        "observes": list(task.env.observed),
        "recipients": [list(r) for r in task.recipient_lists],
        "slot_senders": task.slot_senders.tolist(),
        "inputs": {INPUTS[0]: ["N", 2, S, S], INPUTS[1]: ["N", slots, K]},
        "outputs": {OUTPUTS[0]: ["N", len(MOVE_NAMES)], OUTPUTS[1]: ["N", head.out_features]},
        "encoding": {
            INPUTS[0]: "float32 0/1: [n, 0, row, col] is 1 at the agent's own cell, [n, 1, row, col] at the goal "
            "cell it observes (agent observes[agent]'s goal)",
            INPUTS[1]: "float32 0/1: [n, s] the K bits sender slot_senders[agent][s] sent task.channel.delay steps "
            "before; zeros when none arrived (or the slot is -1, or the episode is younger than the delay)",
            OUTPUTS[0]: "move argmax (greedy) or drawn from softmax; move m is moves[m], changing (row, col) by "
            "move_deltas[m]",
            OUTPUTS[1]: message,
        },
        "opset": OPSET,
        "task": task.to_dict(),
    }


def write_graph(controller: Controller, path: Path) -> None:
    """The policy network, bare (no card), as ONNX at `path`, batch axis `N` dynamic."""
    task = controller.task
    example = (torch.zeros(1, 2, task.env.size, task.env.size), torch.zeros(1, task.slots, task.channel.bits))
    # torch < 2.5 has no `dynamo` argument and exports with the TorchScript exporter anyway
    legacy: dict[str, Any] = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
    with warnings.catch_warnings():
        # the TorchScript exporter is chosen on purpose (module docstring), so its deprecation notices are
        # noise here; the tracer's "torch.tensor ... registered as constants" is about the powers of two
        # that read bits as a message index, which are constants for a given K
        warnings.filterwarnings("ignore", message=".*TorchScript-based ONNX export", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.onnx\._internal\.torchscript")
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        with torch.no_grad():  # the acting graph (PolicyNet._first_conv takes a training-only path otherwise)
            torch.onnx.export(
                controller.policy.eval(),
                example,
                str(path),
                **legacy,
                opset_version=OPSET,
                input_names=list(INPUTS),
                output_names=list(OUTPUTS),
                dynamic_axes={name: {0: "N"} for name in INPUTS + OUTPUTS},
            )


def export_onnx(controller: Controller, path: str | Path) -> dict[str, Any]:
    """Write `path` (the graph, its card in the metadata) and `<path>.json` (the card); returns the card."""
    onnx = require("onnx")
    card = policy_card(controller)
    path = Path(path)

    def write(tmp: Path) -> None:  # renamed into place once whole: a robot never loads half a file
        write_graph(controller, tmp)
        model = onnx.load(str(tmp))
        model.metadata_props.add(key=METADATA_KEY, value=json.dumps(card))
        onnx.checker.check_model(model)
        onnx.save(model, str(tmp))

    write_atomic(path, write)
    write_text_atomic(sidecar_path(path), json.dumps(card, indent=2) + "\n")
    return card
