"""``--cpu-durations=N``: the N tests that used the most CPU, at the end of the run, as
``--durations`` lists the slowest in wall time (issue 33: the suite's CPU budget; the whole
run's CPU, every process's, is tools/suite_cpu.py's).

A test's CPU is its setup, call and teardown in the test's process (all its threads: the
daemons a test runs in process included) plus the children that process reaped meanwhile
(``getrusage`` of the process and of its reaped children: a daemon, a servo or a sensing
child the test started and waited for; not a process still running after it, nor a module
or session fixture's work after the test that set it up). With xdist each worker measures
its tests and the numbers reach the controller in the reports (``user_properties``).
"""

from __future__ import annotations

import resource
from collections import defaultdict

import pytest

CPU_PROPERTY = "cpu_s"
_PHASE_CPU = pytest.StashKey[float]()
_totals: dict[str, float] = defaultdict(float)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--cpu-durations", type=int, default=0, metavar="N",
        help="list the N tests that used the most CPU (s), setup and teardown included",
    )  # fmt: skip


def process_cpu_s() -> float:
    """CPU s of this process (all its threads) and of the children it has reaped."""
    own, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _phase(item: pytest.Item):
    if not item.config.getoption("cpu_durations"):
        return (yield)
    t0 = process_cpu_s()
    try:
        return (yield)
    finally:
        item.stash[_PHASE_CPU] = process_cpu_s() - t0


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item):
    return (yield from _phase(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item):
    return (yield from _phase(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None):
    return (yield from _phase(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    report = yield
    cpu = item.stash.get(_PHASE_CPU, None)
    if cpu is not None:
        report.user_properties.append((CPU_PROPERTY, round(cpu, 3)))
        del item.stash[_PHASE_CPU]
    return report


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    for key, value in report.user_properties:
        if key == CPU_PROPERTY:
            _totals[report.nodeid] += value


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    n = config.getoption("cpu_durations")
    if not n or not _totals:
        return
    terminalreporter.write_sep("=", f"{n} tests that used the most CPU")
    for nodeid, cpu in sorted(_totals.items(), key=lambda kv: -kv[1])[:n]:
        terminalreporter.write_line(f"{cpu:7.2f} CPU-s  {nodeid}")
    terminalreporter.write_line(
        f"{sum(_totals.values()):7.1f} CPU-s in all {len(_totals)} tests (their processes and "
        "the children they reaped; collection and the workers' start not included)"
    )
