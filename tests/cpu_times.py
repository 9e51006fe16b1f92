"""`--cpu-times N`: the N tests, and the N groups (`tests/scheduling.py`), that cost the most
CPU seconds, measured in the process that ran them (with or without xdist).

A test's CPU is its process's own (every thread: the merge's in-process services too) and
its reaped children's (the services a test started and stopped, the CLI's runs), from its
setup to its teardown; a session fixture's cost falls on the first test that uses it.
Processes reaped only at the session's end (the extraction pools' forkserver and its
workers, the session aligner) fall on no test. On a loaded machine CPU seconds compare
where wall seconds do not."""

from __future__ import annotations

import resource

import pytest

from tests.scheduling import group_of

_START = pytest.StashKey[float]()
_SEEN: dict[str, float] = {}  # test id -> CPU seconds, as reported (on the controller)


def cpu_s() -> float:
    """CPU seconds of this process and its reaped children, user and system."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--cpu-times",
        type=int,
        default=None,
        metavar="N",
        help="show the N tests and groups that took the most CPU seconds",
    )


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.config.getoption("--cpu-times") is not None:
        item.stash[_START] = cpu_s()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """The teardown's report carries the test's CPU seconds (to xdist's controller too)."""
    outcome = yield
    if call.when == "teardown" and _START in item.stash:
        outcome.get_result().user_properties.append(("cpu_s", cpu_s() - item.stash[_START]))


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when != "teardown":
        return
    for key, value in report.user_properties:
        if key == "cpu_s":
            _SEEN[report.nodeid] = value


def pytest_terminal_summary(terminalreporter, exitstatus, config: pytest.Config) -> None:
    n = config.getoption("--cpu-times")
    times = _SEEN
    if n is None or not times:
        return
    groups: dict[str, float] = {}
    for nodeid, s in times.items():
        groups[group_of(nodeid)] = groups.get(group_of(nodeid), 0.0) + s
    tr = terminalreporter
    tr.write_sep("=", f"CPU seconds: {sum(times.values()):.0f} in {len(times)} tests")
    for title, rows in (("tests", times), ("groups", groups)):
        tr.write_line(f"the {n} costliest {title}:")
        for name, s in sorted(rows.items(), key=lambda kv: -kv[1])[:n]:
            tr.write_line(f"{s:8.1f}  {name}")
