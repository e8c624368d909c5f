"""`OnnxController`: a policy exported by `bitcomm export`, run by onnxruntime with numpy, no torch needed.

    controller = OnnxController.load("policy.onnx")
    move, bits = controller.act(planes, received_bits)               # as `bitcomm.Controller.act`

The ONNX graph is the policy network only: `planes` float32 `(N, 2, S, S)` and `received` float32
`(N, slots, K)` bits in, `move_logits` `(N, 5)` and `message_logits` `(N, K)` (bitwise) or
`(N, 2^K)` (onehot) out. Sampling stays outside the graph, here, drawing from the same distributions
`bitcomm.policies.agent.act` draws from: a move from softmax(move_logits); for bitwise messages each bit with
probability sigmoid(logit); for onehot messages an index from softmax(message_logits), sent as its K bits
(most significant first). What a robot needs to use the file (grid size, bits, slots, head, tensor
names, provenance) is stored in the model's metadata under `bitcomm` and in a JSON sidecar
(`policy.onnx.json`), both written by `bitcomm.policies.onnx_export`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from bitcomm.channel.core import index_to_bits
from bitcomm.config import MAX_JOBS, Seed, TaskConfig, check_bool, check_seed
from bitcomm.envs.core import N_MOVES
from bitcomm.errors import ConfigError, bad_value, is_integer
from bitcomm.policies.agent_policies import agent_batch

FORMAT = "bitcomm-onnx-policy"
VERSION = 1
METADATA_KEY = "bitcomm"
INPUTS = ("planes", "received")
OUTPUTS = ("move_logits", "message_logits")
INSTALL_HINT = "pip install bitcomm[onnx]"


def require(module: str) -> Any:
    """Import an optional dependency of the `onnx` extra, or stop with one line saying how to get it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ConfigError(f"{module} is not installed: {INSTALL_HINT}") from None


def sidecar_path(onnx_path: str | Path) -> Path:
    """Where the JSON card of an exported policy lives: next to it, `<file>.json`."""
    p = Path(onnx_path)
    return p.with_name(p.name + ".json")


# ---------------------------------------------------------------------- sampling, as bitcomm.policies.agent.act
def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)  # type: ignore[no-any-return]


def _categorical(logits: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One index per row, drawn from softmax(logits) by inverting its CDF."""
    cdf = np.cumsum(_softmax(logits.astype(np.float64)), -1)
    u = rng.random((logits.shape[0], 1))
    return np.minimum((cdf < u).sum(-1), logits.shape[-1] - 1).astype(np.int64)  # type: ignore[no-any-return]


def _message_bits(kind: str, logits: np.ndarray, bits: int, greedy: bool, rng: np.random.Generator) -> np.ndarray:
    """`(N, K)` uint8 bits from message logits, as `bitcomm.policies.heads` mode/sample do."""
    if kind == "bitwise":
        if greedy:
            return (logits > 0).astype(np.uint8)
        p_one = 0.5 * (1.0 + np.tanh(0.5 * logits.astype(np.float64)))  # sigmoid, without overflow
        return (rng.random(logits.shape) < p_one).astype(np.uint8)
    index = logits.argmax(-1) if greedy else _categorical(logits, rng)
    return index_to_bits(index, bits)


def check_card(path: str | Path, metadata: Any) -> None:
    """One line unless `metadata` is a policy card this bitcomm reads: format, version, task and head."""

    def bad(why: str) -> ConfigError:
        return ConfigError(f"invalid onnx={str(path)!r}: {why}")

    if not isinstance(metadata, dict) or metadata.get("format") != FORMAT:
        raise bad("no bitcomm policy card in it (made by bitcomm export?)")
    version = metadata.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise bad(f"its card's version {version!r} is not a whole number")
    if version > VERSION:
        raise bad(f"format version {version} is newer than this bitcomm reads ({VERSION})")
    if metadata.get("messages") not in ("bitwise", "onehot"):
        raise bad(f"its card's messages {metadata.get('messages')!r} is not bitwise or onehot")
    try:
        TaskConfig.from_dict(metadata["task"])
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        why = "no task" if isinstance(err, KeyError) and err.args == ("task",) else f"{type(err).__name__}: {err}"
        raise bad(f"its card does not describe the task it plays ({why})") from None


def card_shapes(metadata: dict[str, Any]) -> list[list[int]]:
    """The shapes, batch axis left out, of the graph's inputs and outputs (`INPUTS`, `OUTPUTS`) that a checked
    card describes."""
    task = TaskConfig.from_dict(metadata["task"])
    bits = task.channel.bits
    messages = bits if metadata["messages"] == "bitwise" else 2**bits
    return [[2, task.env.size, task.env.size], [task.slots, bits], [N_MOVES], [messages]]


class OnnxController:
    """An exported policy network in an onnxruntime session, acting for any agent of its task."""

    def __init__(self, session: Any, metadata: dict[str, Any], seed: Seed = 0) -> None:
        self.session = session
        self.metadata = metadata
        """The policy card written by `bitcomm export` (also in the `.json` sidecar)."""
        self.task: TaskConfig = TaskConfig.from_dict(metadata["task"])
        self.messages: str = metadata["messages"]
        if seed is not None and not isinstance(seed, np.random.SeedSequence):
            check_seed(seed)  # as Controller's: numpy refuses -1 or 1.5 in words naming neither, and takes True
        self.rng = np.random.default_rng(seed)

    @classmethod
    def load(cls, path: str | Path, seed: Seed = 0, threads: int = 1) -> OnnxController:
        """From a `.onnx` file written by `bitcomm export`; `seed` drives sampling, `threads` onnxruntime."""
        if not is_integer(threads) or not 1 <= threads <= MAX_JOBS:  # type: ignore[operator]
            # onnxruntime refused "2" or 2.5 in a TypeError, and a billion in a MemoryError read as a bad file
            raise bad_value("threads", threads, f"must be an integer in [1, {MAX_JOBS}]")
        ort = require("onnxruntime")
        if Path(path).is_dir():  # a run folder, or export's: "no such file" would send the user looking for one
            raise ConfigError(f"invalid onnx={str(path)!r}: is a folder; give the .onnx file `bitcomm export` wrote")
        if not Path(path).is_file():
            raise ConfigError(f"invalid onnx={str(path)!r}: no such file")
        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = int(threads)
        try:
            session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own error types for unreadable models
            raise ConfigError(f"invalid onnx={str(path)!r}: not an ONNX model ({type(err).__name__})") from None
        card = session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
        try:
            metadata = json.loads(card) if card else {}
        except ValueError:
            metadata = {}
        check_card(path, metadata)
        tensors = (*session.get_inputs(), *session.get_outputs())
        names = tuple(t.name for t in tensors[:2]), tuple(t.name for t in tensors[2:])
        if names != (INPUTS, OUTPUTS):
            raise ConfigError(f"invalid onnx={str(path)!r}: tensors {names} are not {(INPUTS, OUTPUTS)}")
        shapes, card = [list(t.shape[1:]) for t in tensors], card_shapes(metadata)
        if shapes != card:  # a card edited by hand, or copied from another export: it would play on the wrong inputs
            raise ConfigError(f"invalid onnx={str(path)!r}: its graph's shapes {shapes} are not its card's {card}")
        return cls(session, metadata, seed)

    def logits(self, planes: np.ndarray, received_bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`(move_logits (N, 5), message_logits (N, out))` for a batch of N agents."""
        move, message = self.session.run(
            list(OUTPUTS),
            {
                "planes": np.ascontiguousarray(planes, dtype=np.float32),
                "received": np.ascontiguousarray(received_bits, dtype=np.float32),
            },
        )
        return move, message

    def act(self, planes: np.ndarray, received_bits: np.ndarray, greedy: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """`(move, message_bits)`: int64 `()` and uint8 `(K,)` for one agent, `(N,)` and `(N, K)` for a batch."""
        planes, received, single = agent_batch(planes, received_bits, self.task)
        greedy = check_bool("greedy", greedy)
        move_logits, message_logits = self.logits(planes, received)
        moves = move_logits.argmax(-1).astype(np.int64) if greedy else _categorical(move_logits, self.rng)
        bits = _message_bits(self.messages, message_logits, self.task.channel.bits, greedy, self.rng)
        return (moves[0], bits[0]) if single else (moves, bits)
