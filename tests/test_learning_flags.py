"""Learning flags are the plain fields of TrainConfig and ModelConfig: read from the source, they agree with
`dataclasses.fields`, cover every recipe key, default to "the recipe's value" and reach the config."""

from __future__ import annotations

import argparse
import dataclasses
import typing

import pytest

from bitcomm.commands.learning_flags import add_learning_flags, learning_overrides, recipe_values
from bitcomm.commands.train import ENV_CONFIG, GRID_CONFIG
from bitcomm.errors import ConfigError
from bitcomm.learn.config import RECIPES, TrainConfig, make_train_config
from bitcomm.learn.env_config import EnvChannelConfig, EnvTrainConfig
from bitcomm.learn.options import STRUCTURAL, field_default, learning_options
from bitcomm.policies.networks import ModelConfig


def plain_fields(cls: type) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        kind = args[0] if len(args) == 1 else kind  # X | None -> X
        if kind in (int, float, bool, str) and f.name not in STRUCTURAL:
            out[f.name] = kind
    return out


def test_every_plain_field_is_a_flag_of_its_type() -> None:
    expected = {**plain_fields(TrainConfig), **plain_fields(ModelConfig)}
    assert {name: o.kind for name, o in learning_options().items()} == expected
    assert {k for recipe in RECIPES.values() for k in recipe} <= set(expected)
    assert {"lr", "num_envs", "adv_norm", "coords", "hidden", "checkpoint_seconds", "mode"} <= set(expected)
    assert learning_options()["epochs"].help == "Passes over each batch (PPO-style reuse when > 1)."


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_learning_flags(parser)
    return parser.parse_args(argv)


def test_flags_default_to_the_recipe_and_override_it() -> None:
    assert learning_overrides(parse()) == {}
    given = learning_overrides(parse("--num-envs", "16", "--lr", "3e-4", "--no-coords", "--adv-norm", "--mode", "a3c"))
    assert given == {"num_envs": 16, "lr": 3e-4, "coords": False, "adv_norm": True, "mode": "a3c"}
    cfg = make_train_config("reinforced", **given)
    assert (cfg.num_envs, cfg.lr, cfg.model.coords, cfg.mode) == (16, 3e-4, False, "a3c")
    assert make_train_config("reinforced", **learning_overrides(parse())) == make_train_config("reinforced")


def test_parse_one_value() -> None:
    options = learning_options()
    assert options["coords"].parse("false") is False and options["adv_norm"].parse("1") is True
    assert options["epochs"].parse("3") == 3 and options["lr"].parse("1e-3") == 1e-3
    for name, text in (("epochs", "1.5"), ("lr", "fast"), ("coords", "maybe")):
        with pytest.raises(ConfigError, match=name):
            options[name].parse(text)


def test_a_config_built_in_python_names_a_wrongly_typed_or_out_of_range_value() -> None:
    bad = {"epochs": 2.5, "num_envs": True, "train_max_steps": -1, "lr": "fast", "clip": float("nan"), "gamma": 1.5}
    for name, value in bad.items():
        with pytest.raises(ConfigError, match=f"{name.replace('_', '-')}={value!r}"):
            make_train_config("reinforced", **{name: value})
    assert make_train_config("reinforced", epochs=2, lr=1, gamma=1).lr == 1  # an int is a number


@pytest.mark.parametrize("seed", [-1, 2**32, 2**70, 2.0, "7"])
def test_a_seed_no_stream_takes_is_one_line_wherever_python_gives_one(seed: object) -> None:
    """`bitcomm train --seed` stops these; from Python they reached numpy's "expected non-negative integer" or
    torch's "Overflow when unpacking long long", naming no seed, once training, evaluation or sampling began."""
    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.evaluation import evaluate
    from bitcomm.policies.networks import PolicyNet
    from bitcomm.policies.reference import OraclePolicy

    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
    for make in (
        lambda: make_train_config("reinforced", task=task, seed=seed),
        lambda: EnvTrainConfig(env="mpe2.simple_v3:parallel_env", seed=seed),  # type: ignore[arg-type]
        lambda: evaluate(OraclePolicy(task), task, 2, seed=seed),  # type: ignore[arg-type]
        lambda: Controller(PolicyNet(task, ModelConfig()), {}, seed=seed),  # type: ignore[arg-type]
    ):
        with pytest.raises(ConfigError, match=f"invalid seed={seed!r}: must be an integer in"):
            make()
    assert make_train_config("reinforced", task=task, seed=2**32 - 1).seed == 2**32 - 1


def test_a_name_that_is_no_learning_option_is_one_line_naming_the_closest() -> None:
    """A typo was the dataclass's TypeError ("unexpected keyword argument"), a list's length where a list goes
    Python's "'int' object is not iterable"."""
    with pytest.raises(ConfigError, match="invalid option='num_env': not a learning option.*did you mean num_envs"):
        make_train_config("reinforced", num_env=16)
    with pytest.raises(ConfigError, match="invalid option='model': not a learning option.*ModelConfig given by name"):
        make_train_config("reinforced", model=ModelConfig())
    with pytest.raises(ConfigError, match="invalid conv_channels=8: one or more integers"):
        make_train_config("reinforced", conv_channels=8)


def test_numpy_numbers_are_stored_as_python_ones_so_a_run_can_record_and_seed_them() -> None:
    """A notebook's sweep hands numpy values (`np.arange`, `np.float32`): a config stores the Python values, so that
    a run writes its config.json and torch takes its seed, where the run stopped in a traceback from json
    ("float32 is not JSON serializable") or from torch ("an integer is required")."""
    import json

    import numpy as np
    import torch

    given = {"seed": np.int64(3), "lr": np.float32(0.5), "num_envs": np.int64(16), "anneal_lr": np.True_}
    cfg = make_train_config("reinforced", hidden=np.int32(8), **given)
    channel = EnvChannelConfig(bits=np.int64(3), flip_prob=np.float32(0.25))
    env_cfg = EnvTrainConfig(env="mpe2.simple_v3:parallel_env", seed=np.uint32(3), lr=np.float32(0.5), channel=channel)
    values = (cfg.seed, cfg.lr, cfg.num_envs, cfg.anneal_lr, cfg.model.hidden, env_cfg.seed, env_cfg.lr, channel.bits)
    assert [type(v) for v in values] == [int, float, int, bool, int, int, float, int]
    json.dumps([cfg.to_dict(), env_cfg.to_dict()])
    torch.Generator().manual_seed(cfg.seed)


def test_a_yes_or_no_option_that_is_not_a_bool_is_one_line_not_read_as_true() -> None:
    """`held_out_greedy="no"` is a truthy string: taken, it played greedily; any non-bool is named."""
    with pytest.raises(ConfigError, match="invalid held-out-greedy='no': must be True or False"):
        make_train_config("reinforced", held_out_greedy="no")
    with pytest.raises(ConfigError, match="invalid plane-coords=1: must be True or False"):
        ModelConfig(plane_coords=1)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="invalid obs-norm='false': must be True or False"):
        EnvTrainConfig(env="mpe2.simple_v3:parallel_env", obs_norm="false")  # type: ignore[arg-type]


def test_a_numpy_seed_drives_a_controllers_sampling_as_the_python_one() -> None:
    """torch's `manual_seed` refuses a numpy integer ("an integer is required"), which `check_seed` takes."""
    import numpy as np
    import torch

    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.networks import PolicyNet

    net = PolicyNet(TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4)), ModelConfig())
    made, python = Controller(net, {}, seed=np.int64(5)), Controller(net, {}, seed=5)
    assert torch.equal(made.generator.get_state(), python.generator.get_state())


def test_a_controllers_greedy_or_generator_of_the_wrong_kind_is_one_line() -> None:
    """`greedy="False"` is a truthy string: taken, it played greedily; a generator that is not a torch one was torch's
    TypeError from deep in its sampling."""
    import numpy as np

    from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.networks import PolicyNet

    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
    controller = Controller(PolicyNet(task, ModelConfig()), {})
    planes, received = np.zeros((2, 4, 4), np.uint8), np.zeros((1, 4), np.uint8)
    with pytest.raises(ConfigError, match="invalid greedy='False': must be True or False"):
        controller.act(planes, received, greedy="False")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="invalid generator=5: must be a torch.Generator"):
        controller.act(planes, received, generator=5)  # type: ignore[arg-type]
    assert controller.act(planes, received, greedy=np.True_)[1].shape == (4,)


def test_a_task_or_config_of_the_wrong_kind_is_named_not_an_attribute_error() -> None:
    """A notebook's likely slip, the grid's EnvConfig where a TaskConfig goes, or a dict for the config."""
    from bitcomm.config import EnvConfig
    from bitcomm.learn.run import train

    with pytest.raises(ConfigError, match=r"invalid task=EnvConfig\(.*must be a bitcomm.TaskConfig"):
        make_train_config("reinforced", task=EnvConfig(size=4))
    with pytest.raises(ConfigError, match="invalid task=.*must be a bitcomm.TaskConfig"):
        TrainConfig(task=EnvConfig(size=4))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"invalid cfg=\{'episodes': 5\}: must be a TrainConfig"):
        train({"episodes": 5}, "never-made")  # type: ignore[arg-type]


def test_the_help_gives_each_recipes_default_as_the_config_has_it() -> None:
    defaults = {f.name: f.default for cls in (TrainConfig, ModelConfig) for f in dataclasses.fields(cls)}
    for name, option in learning_options().items():
        assert option.default == defaults[name], name  # read from the source without importing it
        for recipe, value in recipe_values(option).items():
            cfg = make_train_config(recipe)
            assert value == getattr(cfg.model if hasattr(cfg.model, name) else cfg, name), (recipe, name)
    helps = {a.dest: a.help for a in parse_actions()}
    assert helps["lr"] == "lr (default: 0.003 under reinforced, 0.001 under supervised and paper)"
    assert helps["critic_lr"] == "critic lr (default: 0.001)"
    assert helps["anneal_lr"].endswith("(default: on under reinforced, off under supervised and paper)")
    assert "marginals" in helps["encoder"]  # the first sentence does not end at "Fig. 2"
    budgets = [field_default(module, cls, "episodes") for module, cls in (GRID_CONFIG, ENV_CONFIG)]
    assert budgets == [defaults["episodes"], EnvTrainConfig(env="x:y").episodes]


def parse_actions() -> list[argparse.Action]:
    parser = argparse.ArgumentParser()
    add_learning_flags(parser)
    return parser._actions
