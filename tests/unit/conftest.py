"""Unit tests run in this process: one that starts a process (a service, a CLI run, a pool
of workers) belongs in tests/process, tests/api or tests/e2e."""

import multiprocessing.process
import subprocess

import pytest


@pytest.fixture(scope="module", autouse=True)
def _no_processes():
    """Module-scoped, so it is in force before the module's own fixtures are built."""

    def refuse(*args, **kwargs):
        raise AssertionError("a unit test started a process: move it out of tests/unit")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(subprocess.Popen, "__init__", refuse)
        mp.setattr(multiprocessing.process.BaseProcess, "start", refuse)
        yield
