"""One torch thread per pytest-xdist process: `make test` runs one process per core, and a second thread on
a busy core costs more than it gives (a run with 2 threads beside another busy core trained 2.9x slower)."""

import os

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


class ThreadWatch:
    """What a command did with torch's threads: each `torch.set_num_threads` call, and the count each watched
    function found when called (`watch`). `want` is a count other than the current one, so setting it shows."""

    def __init__(self, monkeypatch) -> None:
        self.monkeypatch = monkeypatch
        self.before = torch.get_num_threads()
        self.want = 1 if self.before != 1 else 2
        self.calls: list[int] = []
        self.seen: list[int] = []
        self._set = torch.set_num_threads

        def record(n: int) -> None:
            self.calls.append(n)
            self._set(n)

        monkeypatch.setattr(torch, "set_num_threads", record)

    def watch(self, owner: object, name: str) -> None:
        real = getattr(owner, name)

        def spy(*args, **kwargs):
            self.seen.append(torch.get_num_threads())
            return real(*args, **kwargs)

        self.monkeypatch.setattr(owner, name, spy)

    def zero_is_one_line(self, command: str, capsys) -> bool:
        """`bitcomm COMMAND --threads 0`: exit status 2 and one error line naming the flag."""
        from bitcomm.cli import main

        capsys.readouterr()
        rc = main([command, "--threads", "0"])
        err = capsys.readouterr().err
        return rc == 2 and err.count("\n") == 1 and "--threads" in err


@pytest.fixture
def threads(monkeypatch):
    """A `ThreadWatch`; torch's thread count is put back afterwards."""
    watch = ThreadWatch(monkeypatch)
    yield watch
    watch._set(watch.before)


@pytest.fixture
def trust_test_envs(monkeypatch, request) -> None:
    """Trust the test module's own toy envs (`f"{__name__}:SomeEnv"`) when a run trained on one is read back, as a
    user vouches for their own env package (`BITCOMM_TRUST_ENVS`, docs/env_learning.md)."""
    monkeypatch.setenv("BITCOMM_TRUST_ENVS", request.module.__name__.split(".")[0])
