"""Keeping freed memory (`bitcomm.learn.allocator`) is set once per process on glibc, and can be turned off."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bitcomm.learn.allocator import _is_glibc

PROBE = "from bitcomm.learn.allocator import keep_freed_memory as k; print(k(), k())"


def _probe(**env: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, env={**os.environ, **env}, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.skipif(not _is_glibc(), reason="mallopt is glibc's")
def test_the_thresholds_are_set_on_glibc_and_setting_them_again_is_a_no_op() -> None:
    assert _probe(BITCOMM_KEEP_FREED_MEMORY="1") == "True True"


def test_the_environment_variable_leaves_malloc_alone() -> None:
    assert _probe(BITCOMM_KEEP_FREED_MEMORY="0") == "False False"
