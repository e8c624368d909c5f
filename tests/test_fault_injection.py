"""Every corrupt or tampered file is refused with one line naming it (exit status 2, no traceback):
`latest.json`, a checkpoint's metadata and bytes, its resume state, config.json and metrics.csv on
`--resume`, an ONNX policy's card; a recorded env the user did not vouch for is never built (its spec is
code the run folder chooses); and the deploy world's control port ignores and counts malformed lines
instead of crashing. Each case runs the real CLI in-process (`bitcomm.cli.main`)."""

from __future__ import annotations

import functools
import json
import os
import shutil
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from bitcomm.checkpoint import resolve
from bitcomm.cli import main
from bitcomm.config import ChannelConfig, EnvConfig, TaskConfig
from bitcomm.errors import ConfigError

TASK = TaskConfig(EnvConfig(size=4, max_steps=16), ChannelConfig(bits=4))
QUICK = ["--threads", "1", "--quiet", "--eval-episodes", "0", "--checkpoint-seconds", "0"]


def refused(capsys: pytest.CaptureFixture[str], argv: list[str], naming: str) -> str:
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = int(e.code or 0)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, (rc, err)
    assert naming in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from bitcomm.learn.config import make_train_config
    from bitcomm.learn.run import train

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("trained") / "run"
    train(make_train_config(task=TASK, num_envs=16, episodes=32, checkpoint_seconds=0.0), out, progress=False)
    return out


@pytest.fixture
def run(trained: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(trained, tmp_path / "run"))


# ---------------------------------------------------------------------------------------------- tampering
def _latest(text: str | bytes) -> Callable[[Path], str]:
    def tamper(run: Path) -> str:
        path = run / "checkpoints" / "latest.json"
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        return "latest.json"

    return tamper


def _metadata(**changes: str | None) -> Callable[[Path], str]:
    """Rewrite the latest checkpoint's safetensors metadata (None removes a key)."""

    def tamper(run: Path) -> str:
        from safetensors import safe_open
        from safetensors.torch import save_file

        file = resolve(run)
        with safe_open(str(file), framework="pt") as f:
            meta, tensors = dict(f.metadata()), {k: f.get_tensor(k) for k in f.keys()}
        for key, value in changes.items():
            if value is None:
                meta.pop(key, None)
            else:
                meta[key] = value
        save_file(tensors, str(file), metadata=meta)
        return file.name

    return tamper


def _resigned(change: Callable[[dict, dict], None]) -> Callable[[Path], str]:
    """Change the latest checkpoint's config and tensors (`change(config, tensors)`) and write it with a checksum
    that fits: a file another bitcomm version wrote, or a hand-made one, that no checksum refuses."""

    def tamper(run: Path) -> str:
        from safetensors import safe_open
        from safetensors.torch import save_file

        from bitcomm.checkpoint import content_sha256

        file = resolve(run)
        with safe_open(str(file), framework="pt") as f:
            meta, tensors = dict(f.metadata()), {k: f.get_tensor(k) for k in f.keys()}
        config = json.loads(meta["config"])
        change(config, tensors)
        meta["config"] = json.dumps(config)
        meta["sha256"] = content_sha256(tensors, meta)
        save_file(tensors, str(file), metadata=meta)
        return file.name

    return tamper


def _without(prefix: str) -> Callable[[dict, dict], None]:
    def change(config: dict, tensors: dict) -> None:
        for key in [k for k in tensors if k.startswith(f"{prefix}.")]:
            del tensors[key]

    return change


def _cut_first(prefix: str) -> Callable[[dict, dict], None]:
    def change(config: dict, tensors: dict) -> None:
        key = next(k for k in tensors if k.startswith(f"{prefix}."))
        tensors[key] = tensors[key][:1].clone()

    return change


def _bytes(cut: Callable[[bytes], bytes], state: bool = False) -> Callable[[Path], str]:
    """Replace the bytes of the latest weights (or state) file."""

    def tamper(run: Path) -> str:
        file = resolve(run)
        if state:
            file = file.with_name(file.name.replace(".safetensors", ".state.pt"))
        file.write_bytes(cut(file.read_bytes()))
        return file.name

    return tamper


def _remove_state(run: Path) -> str:
    file = resolve(run)
    file.with_name(file.name.replace(".safetensors", ".state.pt")).unlink()
    return "state.pt"


def _file(name: str, content: bytes | None) -> Callable[[Path], str]:
    """Overwrite (None: remove) a file of the run folder."""

    def tamper(run: Path) -> str:
        if content is None:
            (run / name).unlink()
        else:
            (run / name).write_bytes(content)
        return name

    return tamper


def _folder_instead(kind: str) -> Callable[[Path], str]:
    """Replace a file of the run with a folder of its name (`kind`: the latest checkpoint's `safetensors` or
    `state.pt`, or a file of the run folder)."""

    def tamper(run: Path) -> str:
        file = run / kind
        if kind in ("safetensors", "state.pt"):
            file = resolve(run).with_suffix("").with_suffix(f".{kind}")
        file.unlink()
        file.mkdir()
        return "is a folder" if kind != "metrics.csv" else "metrics.csv"

    return tamper


def _flip(data: bytes) -> bytes:
    return data[:-1] + bytes([data[-1] ^ 0x01])


CASES: dict[str, Callable[[Path], str]] = {
    "latest: checkpoint is a number": _latest('{"checkpoint": 5}'),
    "latest: not JSON": _latest("{not json"),
    "latest: a JSON list": _latest("[1]"),
    "latest: empty": _latest(""),
    "latest: binary": _latest(b"\xff\xfe\x00garbage"),
    "latest: checkpoint missing": _latest('{"episodes": 32}'),
    "latest: names a missing file": _latest('{"checkpoint": "ckpt_000000999.safetensors", "episodes": 999}'),
    "latest: names a folder": _folder_instead("safetensors"),
    "latest: names a state file": _latest('{"checkpoint": "ckpt_000000032.state.pt", "episodes": 32}'),
    "latest: episodes disagree": _latest('{"checkpoint": "ckpt_000000032.safetensors", "episodes": "32"}'),
    "latest: parent traversal": _latest('{"checkpoint": "../../x.safetensors"}'),
    "latest: absolute path": _latest('{"checkpoint": "/etc/passwd"}'),
    "metadata: version abc": _metadata(version="abc"),
    "metadata: version -1": _metadata(version="-1"),
    "metadata: version a superscript digit": _metadata(version="²"),  # a digit to str.isdigit, not to int()
    "metadata: version from the future": _metadata(version="99"),
    "metadata: no format": _metadata(format=None),
    "metadata: config not JSON": _metadata(config="{oops"),
    "metadata: episodes changed": _metadata(episodes="1000000"),
    "metadata: checksum removed": _metadata(sha256=None),
    "weights: a flipped byte": _bytes(_flip),
    "weights: truncated": _bytes(lambda d: d[: len(d) // 2]),
    "weights: empty": _bytes(lambda d: b""),
    "weights: header length garbage": _bytes(lambda d: b"\xff" * 8 + d[8:]),
    "checksummed: config's model not an object": _resigned(lambda c, t: c.update(model=5)),
    "checksummed: a policy tensor of the wrong shape": _resigned(_cut_first("policy")),
    "checksummed: no policy weights": _resigned(_without("policy")),
}
RESUME_CASES: dict[str, Callable[[Path], str]] = {
    "checksummed: a config field this bitcomm does not know": _resigned(lambda c, t: c.update(colour="red")),
    "checksummed: config without its task": _resigned(lambda c, t: c.pop("task")),
    "checksummed: a critic tensor of the wrong shape": _resigned(_cut_first("critic")),
    "checksummed: no critic weights": _resigned(_without("critic")),
    "state: missing": _remove_state,
    "state: a flipped byte": _bytes(_flip, state=True),
    "state: truncated": _bytes(lambda d: d[:100], state=True),
    "state: a folder": _folder_instead("state.pt"),
    "config.json: not JSON": _file("config.json", b'{"task": '),
    "config.json: a JSON list": _file("config.json", b"[1]"),
    "config.json: binary": _file("config.json", b"\x00\xff\xfe"),
    "config.json: missing": _file("config.json", None),
    "config.json: starts not a list": _file("config.json", b'{"starts": 5}'),
    "config.json: starts of numbers": _file("config.json", b'{"starts": [1]}'),
    "metrics.csv: binary": _file("metrics.csv", b"\xff\xfe\x00\x01garbage\n\x00\n"),
    "metrics.csv: batch not a number": _file("metrics.csv", b"batch,episodes\nabc,16\n2,32\n"),
    "metrics.csv: a folder": _folder_instead("metrics.csv"),
    "metrics.csv: no batch column": _file("metrics.csv", b"episodes,agent_steps\n16,100\n32,200\n"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_tampered_checkpoint_is_refused_by_eval(case: str, run: Path, capsys) -> None:
    name = CASES[case](run)
    refused(capsys, ["eval", str(run), "--episodes", "10"], naming=name)


@pytest.mark.parametrize("case", [*CASES, *RESUME_CASES])
def test_a_tampered_run_is_not_resumed(case: str, run: Path, capsys) -> None:
    name = {**CASES, **RESUME_CASES}[case](run)
    before = sorted(p.name for p in (run / "checkpoints").iterdir())
    argv = ["train", "--out", str(run), "--resume", "--episodes", "48", *QUICK]
    refused(capsys, argv, naming=name)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == before  # nothing written


@pytest.mark.parametrize("case", [c for c in RESUME_CASES if c.startswith("config.json")])
def test_a_damaged_config_json_stops_a_resume_before_it_prints_a_line(case: str, run: Path, capsys) -> None:
    """It was read only once training began, after "run folder: ... (resumed)": two lines for one mistake."""
    RESUME_CASES[case](run)
    try:
        main(["train", "--out", str(run), "--resume", "--episodes", "48", *QUICK])
    except SystemExit:
        pass
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1, (out, err)


def test_a_wrapped_env_checkpoint_whose_config_does_not_fit_is_one_line(tmp_path: Path, capsys) -> None:
    """eval and render read a wrapped env's config from the checkpoint: a channel field this bitcomm does not
    know is one line naming the file, as on --resume."""
    from bitcomm.checkpoint import save_checkpoint

    config = {"env": "mpe2.simple_speaker_listener_v4:parallel_env", "channel": {"colour": "red"}}
    save_checkpoint(tmp_path, config, {"policy": {"w": torch.zeros(1)}}, 16, 1, {})
    refused(capsys, ["eval", str(tmp_path), "--episodes", "2"], naming="ckpt_000000016.safetensors")
    refused(capsys, ["render", str(tmp_path), "--out", str(tmp_path / "e.gif")], naming="ckpt_000000016.safetensors")


def test_a_grid_checkpoint_under_a_wrapped_envs_config_json_is_one_line(run: Path, capsys) -> None:
    """A run folder's config.json says which loader reads it; a hand-edited one naming a wrapped env over a grid
    run's checkpoint is one line naming the checkpoint, not a KeyError."""
    (run / "config.json").write_text(json.dumps({"env": "mpe2.simple_speaker_listener_v4:parallel_env", "channel": {}}))
    refused(capsys, ["eval", str(run), "--episodes", "2"], naming=resolve(run).name)
    refused(capsys, ["render", str(run), "--out", str(run / "e.gif")], naming=resolve(run).name)


def test_a_torn_last_metrics_row_is_dropped_on_resume(run: Path, capsys) -> None:
    """A kill in the middle of a row leaves it short: that row (past the checkpoint anyway) goes."""
    metrics = run / "metrics.csv"
    metrics.write_text(metrics.read_text() + "3,48,")
    assert main(["train", "--out", str(run), "--resume", "--episodes", "48", *QUICK]) == 0
    rows = metrics.read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["1", "2", "3"]


# ---------------------------------------------------------------------------------------------- recorded envs
MPE = "mpe2.simple_speaker_listener_v4:parallel_env"
MINE = f"{__name__}:speaker_listener"


def speaker_listener(**kwargs: Any) -> Any:
    """A user's own env package: mpe2's speaker-listener under a name no trusted package owns."""
    from mpe2 import simple_speaker_listener_v4

    return simple_speaker_listener_v4.parallel_env(**kwargs)


@pytest.fixture(scope="module")
def env_trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from bitcomm.learn.env_config import EnvTrainConfig
    from bitcomm.learn.env_run import train_env

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("env") / "run"
    train_env(EnvTrainConfig(MINE, num_envs=4, episodes=8, hidden=(8, 8), checkpoint_seconds=0.0), out, progress=False)
    return out


@pytest.fixture
def env_run(env_trained: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of a run on the user's env, read with only the default packages trusted."""
    monkeypatch.delenv("BITCOMM_TRUST_ENVS", raising=False)
    return Path(shutil.copytree(env_trained, tmp_path / "run"))


def _recorded_env(spec: str, **kwargs: Any) -> Callable[[Path], str]:
    """Make the run name another env: in config.json and in its latest checkpoint, re-signed."""
    resign = _resigned(lambda c, t: c.update(env=spec, env_kwargs=kwargs))

    def tamper(run: Path) -> str:
        record = json.loads((run / "config.json").read_text())
        (run / "config.json").write_text(json.dumps({**record, "env": spec, "env_kwargs": kwargs}))
        return resign(run)

    return tamper


def test_a_run_naming_os_system_as_its_env_runs_nothing(env_run: Path, tmp_path: Path, capsys) -> None:
    """eval, render and --resume refuse, before importing anything, an env the user did not vouch for, with one
    line saying how to vouch for it."""
    pwned = tmp_path / "PWNED"
    _recorded_env("os:system", command=f"touch {pwned}")(env_run)
    for argv in (
        ["eval", str(env_run), "--episodes", "2"],
        ["render", str(env_run), "--out", str(tmp_path / "e.gif")],
        ["train", "--resume", "--out", str(env_run), "--episodes", "16", *QUICK],
    ):
        line = refused(capsys, argv, naming="invalid env='os:system'")
        assert "--env os:system" in line and "BITCOMM_TRUST_ENVS=os" in line
    assert not pwned.exists()


def test_a_trusted_package_vouches_only_for_factories_it_defines() -> None:
    """mpe2's factories are made by pettingzoo's `parallel_wrapper_fn`: trusted; a function a pettingzoo module
    merely imported is not pettingzoo's."""
    from bitcomm.envs.factory import check_recorded_env

    check_recorded_env(MPE, "config.json")
    with pytest.raises(ConfigError, match="'defaultdict' is defined in 'collections', outside the trusted packages"):
        check_recorded_env("pettingzoo.utils.conversions:defaultdict", "config.json")


speaker_listener_partial = functools.partial(speaker_listener)  # a user's factory with its arguments bound
system_partial = functools.partial(os.system)


def test_a_trusted_packages_partial_is_judged_by_the_function_it_binds(monkeypatch) -> None:
    """A partial object's own module is functools: the function it calls says where its code is, as for a function."""
    from bitcomm.envs.factory import check_recorded_env

    monkeypatch.setenv("BITCOMM_TRUST_ENVS", __name__)
    check_recorded_env(f"{__name__}:speaker_listener_partial", "config.json")
    with pytest.raises(ConfigError, match=f"'system_partial' is defined in '{os.system.__module__}', outside the"):
        check_recorded_env(f"{__name__}:system_partial", "config.json")


def test_bitcomm_trust_envs_lets_a_users_env_package_through(env_run: Path, monkeypatch, capsys) -> None:
    refused(capsys, ["eval", str(env_run), "--episodes", "2"], naming=f"BITCOMM_TRUST_ENVS={__name__}")
    monkeypatch.setenv("BITCOMM_TRUST_ENVS", f"labenvs, {__name__}")
    assert main(["eval", str(env_run), "--episodes", "2"]) == 0


def test_an_mpe2_run_evaluates_with_nothing_trusted_by_hand(env_run: Path) -> None:
    _recorded_env(MPE)(env_run)  # the same env under its trusted name
    assert main(["eval", str(env_run), "--episodes", "2"]) == 0


def test_a_resume_with_the_recorded_env_typed_trusts_it(env_run: Path, capsys) -> None:
    argv = ["train", "--resume", "--out", str(env_run), "--episodes", "16", *QUICK]
    refused(capsys, argv, naming=f"type --env {MINE}")
    assert main([*argv, "--env", MINE]) == 0


# ---------------------------------------------------------------------------------------------- ONNX
@pytest.fixture(scope="module")
def exported(trained: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from bitcomm.policies.controller import Controller
    from bitcomm.policies.onnx_export import export_onnx

    out = tmp_path_factory.mktemp("onnx") / "policy.onnx"
    export_onnx(Controller.load(trained), out)
    return out


def _card(path: Path, change: Callable[[dict], object]) -> None:
    import onnx

    from bitcomm.policies.onnx_policy import METADATA_KEY

    model = onnx.load(str(path))
    for prop in model.metadata_props:
        if prop.key == METADATA_KEY:
            card = json.loads(prop.value)
            new = change(card)
            prop.value = new if isinstance(new, str) else json.dumps(card)
    onnx.save(model, str(path))


ONNX_CASES: dict[str, Callable[[dict], object]] = {
    "card without task": lambda c: c.pop("task") and None,
    "card task not a dict": lambda c: c.update(task=[1, 2]),
    "card task with an unknown field": lambda c: c["task"]["env"].update(colour="red"),
    "card task with a bad size": lambda c: c["task"]["env"].update(size=-3),
    "card version abc": lambda c: c.update(version="abc"),
    "card version from the future": lambda c: c.update(version=99),
    "card without messages": lambda c: c.pop("messages") and None,
    "card of another grid size": lambda c: c["task"]["env"].update(size=5),
    "card of another head": lambda c: c.update(messages="onehot"),
    "card of another bit count": lambda c: c["task"]["channel"].update(bits=3),
    "card not JSON": lambda c: "{not json",
    "card a JSON list": lambda c: "[1]",
}


@pytest.mark.parametrize("case", list(ONNX_CASES))
def test_a_tampered_onnx_card_is_refused(case: str, exported: Path, tmp_path: Path, capsys) -> None:
    path = Path(shutil.copy(exported, tmp_path / "policy.onnx"))
    _card(path, ONNX_CASES[case])
    argv = ["deploy", "--onnx", str(path), "--episodes", "2", "--timeout", "30"]
    refused(capsys, argv, naming=str(path))


def test_a_garbage_onnx_file_is_refused(tmp_path: Path, capsys) -> None:
    pytest.importorskip("onnxruntime")
    path = tmp_path / "policy.onnx"
    path.write_bytes(b"\x08\x01garbage")
    refused(capsys, ["deploy", "--onnx", str(path), "--episodes", "2"], naming=str(path))
    refused(capsys, ["eval", str(path), "--episodes", "2"], naming=str(path))  # not a checkpoint either


# ---------------------------------------------------------------------------------------------- control port
MALFORMED = [
    b"[1]", b"not json", b"\xff\xfe", b"{}", b'"move"', b"null", b'{"type": "move"}',
    b'{"type": "move", "episode": 0, "t": 0, "move": 7}', b'{"type": "move", "episode": 0, "t": 0, "move": true}',
    b'{"type": "move", "episode": 1, "t": 0, "move": 2}', b'{"type": "stats", "sent": 1}',
]  # fmt: skip
"""Lines an agent's control connection may carry that are no move for episode 0, step 0."""


def test_the_control_port_ignores_and_counts_malformed_lines() -> None:
    from bitcomm.deploy.protocol import LineSocket
    from bitcomm.deploy.world import DeployError, _Agents, _move_of

    agents = _Agents(0, time.monotonic() + 30)  # no agent processes: the test plays agent 0
    client = socket.create_connection(agents.listener.getsockname())
    try:
        server, _ = agents.listener.accept()
        agents.n, agents.conns, agents.udp_ports = 1, [LineSocket(server)], [0]
        client.sendall(b"\n".join([*MALFORMED, b'{"type": "move", "episode": 0, "t": 0, "move": 2}']) + b"\n")
        reply = agents.recv(0, 5.0, "move", _move_of(0, 0))
        assert reply["move"] == 2 and agents.malformed == len(MALFORMED)
        client.sendall(b"[1]\n")
        ignored = rf"did not answer within 0.3 s \({len(MALFORMED) + 1} malformed control lines ignored\)"
        with pytest.raises(DeployError, match=ignored):
            agents.recv(0, 0.3, "move", _move_of(0, 1))  # still bounded: no valid reply, no hang
    finally:
        client.close()
        agents.close()


def test_strangers_on_the_control_port_do_not_stop_a_deploy(monkeypatch: pytest.MonkeyPatch) -> None:
    from bitcomm.deploy import run_deploy
    from bitcomm.deploy import world as world_module
    from bitcomm.policies.source import PolicySource

    strangers: list[socket.socket] = []
    hellos = [b"[1]\n", b"not json\n", b'{"agent": 0, "udp_port": 9}\n', b'{"agent": 0, "token": "guess"}\n']

    class Pestered(world_module._Agents):
        def __init__(self, n: int, end: float) -> None:
            super().__init__(n, end)
            for hello in hellos:  # queued before the agents (still importing) connect
                s = socket.create_connection(self.listener.getsockname())
                s.sendall(hello)
                strangers.append(s)

    monkeypatch.setattr(world_module, "_Agents", Pestered)
    task = TaskConfig(EnvConfig(size=4), ChannelConfig(bits=4))
    try:
        result = run_deploy(PolicySource("oracle"), task, 5, seed=1, deadline_ms=50, timeout_s=60)
    finally:
        for s in strangers:
            s.close()
    assert len(result.outcomes) == 5 and result.summary.success_rate == 1.0
    assert result.network["control_malformed"] == len(hellos)
    assert np.isfinite(result.summary.mean_episode_length)
