"""The learning options of `bitcomm train` and `bitcomm compare`, derived from the config dataclasses.

Every plain option (an int, float, bool or str field) of `TrainConfig` and of `ModelConfig` is an
option named after its field, with the first sentence of the field's docstring as help; a field added
to either dataclass is an option (a flag of both commands, `bitcomm.commands.learning_flags`, and a
`--vary` axis of `bitcomm compare`) with no edit here. Fields that say *what* is trained rather than
*how* (`STRUCTURAL`: the task, the technique, the seed, the budget) are not options.

The fields are read from the two classes' source rather than by importing them: importing the
networks means importing torch, and every `bitcomm` command builds every parser. Field docstrings
exist only in the source anyway. `tests/test_learning_flags.py` holds this reading to
`dataclasses.fields`.
"""

from __future__ import annotations

import ast
import importlib.util
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from bitcomm.errors import bad_value

STRUCTURAL = frozenset({"task", "model", "recipe", "estimator", "messages", "seed", "episodes"})
"""Config fields that are not learning options; each command has its own flags for them."""
SOURCES = (("bitcomm.learn.config", "TrainConfig"), ("bitcomm.policies.networks", "ModelConfig"))
"""Where the learning options are defined, in flag order."""
PLAIN_TYPES: dict[str, type] = {"int": int, "float": float, "bool": bool, "str": str}


@dataclass(frozen=True)
class Option:
    """One plain config field as a command-line option."""

    name: str
    """The field's name, also the argparse dest (`num_envs`)."""
    kind: type
    """int, float, bool or str."""
    help: str | None
    default: Any = None
    """The dataclass field's default: the value where a recipe sets none."""

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def parse(self, text: str) -> Any:
        """A value as typed on a command line (`--vary lr=1e-3,3e-4`, say), or one error line."""
        text = text.strip()
        if self.kind is bool:
            value = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}.get(text.lower())
            if value is None:
                raise bad_value(self.name, text, "must be true or false")
            return value
        try:
            return self.kind(text)
        except ValueError:
            raise bad_value(self.name, text, f"must be {'an integer' if self.kind is int else 'a number'}") from None


def _plain_type(annotation: ast.expr) -> type | None:
    """`int`, `float`, `bool`, `str`, also as `X | None`; None for anything else (tuples, configs)."""
    text = ast.unparse(annotation).replace(" ", "")
    for suffix in ("|None", ""):
        if text.endswith(suffix) and text[: len(text) - len(suffix)] in PLAIN_TYPES:
            return PLAIN_TYPES[text[: len(text) - len(suffix)]]
    return None


def _first_sentence(doc: str) -> str:
    text = " ".join(doc.replace("`", "").split())
    sentence = re.split(r"(?<!Fig\.)(?<!e\.g\.)(?<!i\.e\.)(?<=\.)\s", text, maxsplit=1)[0]  # not at "Fig. 2"
    return sentence.replace("%", "%%")  # argparse formats help with %


def _class_body(module: str, cls: str) -> list[ast.stmt]:
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise ImportError(f"cannot find {module}")
    tree = ast.parse(Path(spec.origin).read_text())
    return next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls).body


def _literal(node: ast.expr | None) -> Any:
    """A field's default as written in the source, where it is a literal (None otherwise)."""
    try:
        return None if node is None else ast.literal_eval(node)
    except ValueError:
        return None


def field_default(module: str, cls: str, name: str) -> Any:
    """The default of the dataclass field `cls.name`, read from `module`'s source (without importing it)."""
    body = _class_body(module, cls)
    node = next(
        n for n in body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name) and n.target.id == name
    )
    return _literal(node.value)


def _class_options(module: str, cls: str) -> list[Option]:
    body = _class_body(module, cls)
    options = []
    for node, after in zip(body, [*body[1:], None], strict=True):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        kind = _plain_type(node.annotation)
        if kind is None or node.target.id in STRUCTURAL:
            continue
        doc = None
        if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str):
            doc = _first_sentence(after.value.value)
        options.append(Option(node.target.id, kind, doc, _literal(node.value)))
    return options


@lru_cache(maxsize=1)
def learning_options() -> dict[str, Option]:
    """Every learning option by name: the plain fields of TrainConfig, then of ModelConfig."""
    return {o.name: o for module, cls in SOURCES for o in _class_options(module, cls)}
