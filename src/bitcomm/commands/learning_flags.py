"""The learning flags of `bitcomm train` and `bitcomm compare`: one per learning option
(`bitcomm.learn.options`), named after its field (`num_envs` -> `--num-envs`, a bool ->
`--coords/--no-coords`), with the field's first docstring sentence as help and None as default:
"the recipe's value" (`bitcomm.learn.recipes.RECIPES`, or the field's default where a recipe sets none),
which the help spells out per recipe. Torch-free: every command builds every parser.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from bitcomm.errors import ConfigError
from bitcomm.learn.options import Option, learning_options
from bitcomm.learn.recipes import DEFAULT_RECIPE, RECIPES


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


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    return f"{value:g}" if isinstance(value, float) else str(value)


def recipe_values(option: Option) -> dict[str, Any]:
    """What `option` is when not given, per recipe: the recipe's value, or the field's default."""
    return {recipe: values.get(option.name, option.default) for recipe, values in RECIPES.items()}


def recipe_defaults(option: Option) -> str:
    """`recipe_values` for the help: `0.01`, or `0.003 under reinforced, 0.001 under supervised and paper`."""
    by_value: dict[str, list[str]] = {}
    for recipe, value in recipe_values(option).items():
        by_value.setdefault(_shown(value), []).append(recipe)
    if len(by_value) == 1:
        return next(iter(by_value))
    return ", ".join(f"{value} under {' and '.join(recipes)}" for value, recipes in by_value.items())


def add_learning_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per learning option, in a group of its own; default None (the recipe's value)."""
    g = parser.add_argument_group(
        f"learning options (default: the --recipe's value; --recipe is {DEFAULT_RECIPE} if not given)"
    )
    for o in learning_options().values():
        text = f"{o.help or o.name.replace('_', ' ')} (default: {recipe_defaults(o)})"
        if o.kind is bool:
            g.add_argument(o.flag, dest=o.name, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            g.add_argument(o.flag, dest=o.name, type=_argparse_type(o), default=None, help=text)


def learning_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The learning options given on the command line, for `make_train_config(recipe, task, **overrides)`."""
    return {name: getattr(args, name) for name in learning_options() if getattr(args, name, None) is not None}
