"""Settings of the whole test run (loaded before any test module, hence before numpy).

One BLAS thread per test process: the suite runs on pytest-xdist workers (``-n``, pytest.ini),
one per core, and OpenBLAS's own threads on top of them made the linear-algebra-heavy tests
(discrepancy, identification) use several times the CPU for the same work. Node processes the
ROS tests start inherit the setting through the environment. ``bench/`` measures speed with the
library defaults; the tests measure nothing that depends on the thread count.
"""
from __future__ import annotations

import os
import resource
from collections.abc import Generator
from typing import Any

import pytest  # neither pytest nor the two above load numpy

for _variable in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_variable] = '1'

_PHASE_START = pytest.StashKey[float]()


#: The modules that take longest (CPU s with ``--cpu-durations``, wall for the ROS graphs;
#: docs/testing.md), most first: collected first, hence sent to the workers first (pytest.ini:
#: ``--dist loadfile --no-loadscope-reorder``), so that none of them starts last and runs alone
#: at the end. Every other module follows in its usual order. test_docs_commands leads: its
#: worker waits while the documented command blocks run in processes of their own, whose
#: longest chain (docs/offline.md's mission, ~25 s CPU one command after another) then ends
#: early.
SLOW_FIRST = (
    'cli/test_docs_commands.py',
    'ros/test_effects.py',
    'cli/test_batch.py',
    'ros/test_shutdown.py',
    'ros/test_calibrator.py',
    'core/discrepancy/test_dipoles_survey.py',
    'core/test_targets.py',
    'core/discrepancy/test_openworld.py',
    'io/test_realworld.py',
    'ros/test_common.py',
    'core/discrepancy/test_analysis.py',
    'pipelines/test_effects_bag.py',
    'cli/test_locate.py',
    'ros/test_demo.py',
    'cli/test_survey.py',
    'reports/test_figures_readable.py',
    'reports/test_survey_report.py',
    'cli/test_interrupts_and_full_disk.py',
    'ros/test_calibration_authentication.py',
    'ros/test_tensor_replay.py',
    'io/test_calibration.py',
    'io/test_bag.py',
    'cli/test_discrepancy.py',
    'core/discrepancy/test_targets.py',
    'cli/test_compensate.py',
    # The ROS modules of 7-24 s wall, longest first (a fresh-clone run at ea9098a: in the
    # usual order test_sim_time, test_tensor and test_target ran last, side by side, and the
    # run's last 45 s had the cores 55-65 % busy).
    'ros/test_sim_time.py',
    'ros/test_lifecycle_requests.py',
    'ros/test_tensor.py',
    'ros/test_target.py',
    'ros/test_input_attacks.py',
    'ros/test_covariance.py',
    'ros/test_compensator.py',
    'ros/test_frames.py',
    'ros/test_channel_timing.py',
)


def dispatch_order(modules: list[str]) -> list[str]:
    """The order the workers take ``modules`` (paths under test/, each once): SLOW_FIRST's, then
    the rest, with the ROS modules (``ros/``) taken out and interleaved one for one with the
    others. A ROS module mostly waits on the clock (node start-ups, discovery, replays:
    test_lifecycle_requests ~16 s wall for 2 s CPU), so beside a module that computes it costs
    no wall time; three at once leave the cores idle (the alphabetical order ran them all at
    the end: the run's last minute had the 2 cores ~50 % busy; SLOW_FIRST's own ROS modules
    in a row, the first 150 s ~80 %)."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    ordered = sorted(modules, key=lambda m: rank.get(m, len(SLOW_FIRST)))  # stable: the rest kept
    ros = [m for m in ordered if m.startswith('ros/')]
    others = [m for m in ordered if not m.startswith('ros/')]
    interleaved = [m for pair in zip(others, ros, strict=False) for m in pair]
    shorter = min(len(ros), len(others))
    return interleaved + ros[shorter:] + others[shorter:]


class KeptCaseMissing(pytest.Item):
    """Fails, naming a parametrized test every case of which its own parameters mark ``slow``
    (``pytest.param(..., marks=pytest.mark.slow)``): ``make test`` would run none of them, where
    the rule (pytest.ini) keeps the first or cheapest case of a class in it. A test marked slow
    whole (on the function, class or module) is not one: its cases carry no mark of their own.
    An item, not a collection error, so that it reads the same on xdist's workers."""

    def runtest(self) -> None:
        pytest.fail(f'every case of {self.name} is marked slow, so `make test` runs none: keep '
                    'the first or cheapest unmarked (pytest.ini)', pytrace=False)

    def reportinfo(self) -> tuple[Any, int, str]:
        return self.path, 0, self.name


def kept_cases_missing(items: list[pytest.Item]) -> list[pytest.Item]:
    """A :class:`KeptCaseMissing` beside each parametrized test all of whose cases are slow."""
    cases: dict[tuple[Any, str], list[bool]] = {}  # (module or class, test) -> slow per case
    for item in items:
        callspec = getattr(item, 'callspec', None)
        if callspec is not None:
            key = (item.parent, getattr(item, 'originalname', item.name))
            cases.setdefault(key, []).append(any(m.name == 'slow' for m in callspec.marks))
    return [KeptCaseMissing.from_parent(parent, name=name)
            for (parent, name), slow in cases.items() if all(slow)]


@pytest.hookimpl(tryfirst=True)  # before -m deselects the slow cases
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.extend(kept_cases_missing(items))
    test_dir = config.rootpath / 'test'

    def module_name(item: pytest.Item) -> str:
        try:
            return item.path.relative_to(test_dir).as_posix()
        except ValueError:
            return str(item.path)

    modules = list(dict.fromkeys(module_name(item) for item in items))
    rank = {name: i for i, name in enumerate(dispatch_order(modules))}
    items.sort(key=lambda item: rank[module_name(item)])  # stable: a module's order kept



def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption('--cpu-durations', type=int, default=None, metavar='N',
                     help='list the N tests with the most CPU time (setup + call + teardown, '
                          'this process and the children it waited for, e.g. node processes): '
                          'on a shared machine wall times (--durations) measure the neighbours')


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    if item.config.getoption('cpu_durations') is not None:
        start = item.stash.get(_PHASE_START, None)
        if start is not None:
            report.user_properties.append(('cpu_s', _cpu_s() - start))
    return report


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    item.stash[_PHASE_START] = _cpu_s()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_call(item: pytest.Item) -> None:
    item.stash[_PHASE_START] = _cpu_s()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    item.stash[_PHASE_START] = _cpu_s()


_CPU_BY_TEST: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    for name, value in report.user_properties:
        if name == 'cpu_s':
            _CPU_BY_TEST[report.nodeid] = _CPU_BY_TEST.get(report.nodeid, 0.0) + float(value)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter,
                            config: pytest.Config) -> None:
    count = config.getoption('cpu_durations')
    if count is None or not _CPU_BY_TEST:
        return
    terminalreporter.write_sep('=', f'most CPU time: {count} of {len(_CPU_BY_TEST)} tests, '
                                    f'{sum(_CPU_BY_TEST.values()):.1f} s in all')
    for nodeid, seconds in sorted(_CPU_BY_TEST.items(), key=lambda kv: -kv[1])[:count]:
        terminalreporter.write_line(f'{seconds:8.2f}s cpu  {nodeid}')
    by_module: dict[str, float] = {}
    for nodeid, seconds in _CPU_BY_TEST.items():
        module = nodeid.split('::')[0]
        by_module[module] = by_module.get(module, 0.0) + seconds
    terminalreporter.write_sep('-', f'by module (one worker runs a module): {len(by_module)}')
    for module, seconds in sorted(by_module.items(), key=lambda kv: -kv[1])[:count]:
        terminalreporter.write_line(f'{seconds:8.2f}s cpu  {module}')
