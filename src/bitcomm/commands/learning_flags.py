"""The learning flags of `bitcomm train` and `bitcomm compare`, derived from the config dataclasses.

Every plain option (an int, float, bool or str field) of `TrainConfig` and of `ModelConfig` is a flag
named after its field (`num_envs` -> `--num-envs`, a bool -> `--coords/--no-coords`), with the first
sentence of the field's docstring as help and None as default: "the recipe's value"
(`bitcomm.train.config.RECIPES`). A field added to either dataclass is a flag of both commands with no
edit here. Fields that say *what* is trained rather than *how* (`STRUCTURAL`: the task, the technique,
the seed, the budget) get flags of their own in each command.

The fields are read from the two classes' source rather than by importing them: importing the
networks means importing torch, and every `bitcomm` command builds every parser. Field docstrings
exist only in the source anyway. `tests/test_learning_flags.py` holds this reading to
`dataclasses.fields`.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from bitcomm.errors import ConfigError, bad_value

STRUCTURAL = frozenset({"task", "model", "recipe", "estimator", "messages", "seed", "episodes"})
"""Config fields that are not learning options; each command has its own flags for them."""
SOURCES = (("bitcomm.train.config", "TrainConfig"), ("bitcomm.networks", "ModelConfig"))
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
    sentence = re.split(r"(?<=\.)\s", text, maxsplit=1)[0]
    return sentence.replace("%", "%%")  # argparse formats help with %


def _class_options(module: str, cls: str) -> list[Option]:
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise ImportError(f"cannot find {module}")
    tree = ast.parse(Path(spec.origin).read_text())
    body = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls).body
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
        options.append(Option(node.target.id, kind, doc))
    return options


@lru_cache(maxsize=1)
def learning_options() -> dict[str, Option]:
    """Every learning option by name: the plain fields of TrainConfig, then of ModelConfig."""
    return {o.name: o for module, cls in SOURCES for o in _class_options(module, cls)}


def _argparse_type(option: Option) -> Callable[[str], Any]:
    """`option.parse` as an argparse type: a word where a number belongs is one usage line naming the flag;
    the bounds are TrainConfig's and ModelConfig's, checked when the config is built."""

    def parse(text: str) -> Any:
        try:
            return option.parse(text)
        except ConfigError:
            kind = "an integer" if option.kind is int else "a number" if option.kind is float else "text"
            raise argparse.ArgumentTypeError(f"invalid value {text!r}: must be {kind}") from None

    parse.__name__ = option.kind.__name__
    return parse


def add_learning_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per learning option, in a group of its own; default None (the recipe's value)."""
    g = parser.add_argument_group("learning options (default: the recipe's value)")
    for o in learning_options().values():
        text = f"{o.help or o.name.replace('_', ' ')} (default: the recipe's value)"
        if o.kind is bool:
            g.add_argument(o.flag, dest=o.name, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            g.add_argument(o.flag, dest=o.name, type=_argparse_type(o), default=None, help=text)


def learning_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The learning options given on the command line, for `make_train_config(recipe, task, **overrides)`."""
    return {name: getattr(args, name) for name in learning_options() if getattr(args, name, None) is not None}
