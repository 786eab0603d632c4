"""Test-session set-up shared by every test.

ROS domain isolation: each pytest process (and each xdist worker) takes a ROS_DOMAIN_ID that no
other running test process holds (an exclusive flock on a file per id), and keeps DDS discovery
on localhost, so parallel test runs on one machine cannot hear each other. Child processes
inherit the id.
"""

from __future__ import annotations

import functools
import importlib
import os
import sys
import time
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pytest

pytest_plugins = ["assertion_check"]  # a test that passes without a check fails

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

_held_lock = None


def _claim_domain() -> int:
    """Claim a free ROS domain id for this process, held until it exits (the project's one
    claiming protocol: piezo_stage.launch.domain)."""
    global _held_lock
    from piezo_stage.launch.domain import claim_domain_id

    domain, _held_lock = claim_domain_id(start=os.getpid() % 100)
    return domain


def pytest_unconfigure(config: pytest.Config) -> None:
    """Release this process's ROS domain claim (closing the lock file)."""
    if _held_lock is not None:
        _held_lock.close()


def pytest_configure(config: pytest.Config) -> None:
    # an xdist worker inherits its controller's environment: it claims a domain of its own, so
    # two workers' graphs never hear each other
    owner = os.environ.get("PYTEST_XDIST_WORKER", "main")
    if (
        "PIEZO_TEST_DOMAIN_ID" not in os.environ
        or os.environ.get("PIEZO_TEST_DOMAIN_OWNER", owner) != owner
    ):
        os.environ["PIEZO_TEST_DOMAIN_ID"] = str(_claim_domain())
        os.environ["PIEZO_TEST_DOMAIN_OWNER"] = owner
    os.environ["ROS_DOMAIN_ID"] = os.environ["PIEZO_TEST_DOMAIN_ID"]
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("MPLBACKEND", "Agg")
    _check_needs_rclpy()
    _restore_sigint()
    _build_font_cache()
    _load_hypothesis_profile(config)


def _restore_sigint() -> None:
    """Take SIGINT back when the session was started with it ignored (a shell's background job,
    a CI runner): an ignored signal is inherited across exec, so every child the tests stop with
    SIGINT (emulators, nodes, launched graphs) would ignore it and hang until its timeout. A
    handled one is reset to the default in the child, as from a terminal."""
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _build_font_cache() -> None:
    """Build matplotlib's font cache once, before any test runs.

    A fresh home has none: the first ``import matplotlib.pyplot`` scans the system fonts with
    ``fc-list`` in a child process, which the unit layer's guard refuses inside a test. Paying it
    here keeps the guard whole and makes the first plotting test independent of the machine's
    history."""
    if _importable("matplotlib"):
        import matplotlib.font_manager  # noqa: F401  (builds or loads the cache)


# --- hypothesis profiles -----------------------------------------------------------------------
#: No deadlines anywhere: time enters tests only as generous timeouts.
#: ``ci``: derandomized (the same examples on every run and machine), no example database;
#: ``dev``: random examples, the database in .hypothesis/ (counterexamples are replayed first);
#: ``fuzz``: random and wide, for ``make fuzz`` (scale with PIEZO_FUZZ_FACTOR, see
#: property_support.examples).
def _load_hypothesis_profile(config: pytest.Config) -> None:
    if not _importable("hypothesis"):
        return
    from hypothesis import HealthCheck, settings

    settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
    settings.register_profile("dev", deadline=None, print_blob=True)
    settings.register_profile(
        "fuzz",
        deadline=None,
        print_blob=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    chosen = config.getoption("--hypothesis-profile", default=None)
    settings.load_profile(chosen or ("ci" if os.environ.get("CI") else "dev"))


# --- test layers -----------------------------------------------------------------------------
#: every test belongs to exactly one of these layers (setup.cfg registers them with `slow`)
LAYERS = ("unit", "ros")


#: the files that take longest, longest first (seconds in a full run on a 2-core host): on two
#: workers a long file started last leaves the other worker idle until it ends
LONGEST = (
    "test_readme_shell.py",  # 280
    "test_demo.py",  # 130
    "test_replay_identification.py",  # 100
    "test_stop_signals.py",  # 85
    "test_node_rig_loop.py",  # 85
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test without its layer is a collection error, not a silent member of no layer. Files
    that hold slow tests run first, the LONGEST first of all (stable order otherwise): on the
    workers the long ones then start early instead of leaving one worker alone at the end
    (``make test`` passes ``--no-loadscope-reorder``: xdist would otherwise order the files by
    their number of tests, and the one-test demo came last)."""
    missing = [
        item.nodeid
        for item in items
        if sum(item.get_closest_marker(layer) is not None for layer in LAYERS) != 1
    ]
    if missing:
        raise pytest.UsageError(
            "tests need exactly one layer marker (unit or ros; "
            "`pytestmark = pytest.mark.unit` in the file): " + ", ".join(missing[:10])
        )
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}

    def rank(item: pytest.Item) -> tuple[int, int]:
        if item.path.name in LONGEST:
            return 0, LONGEST.index(item.path.name)
        return (1 if item.path in slow_files else 2), 0

    items.sort(key=rank)


# --- modules that need rclpy -------------------------------------------------------------------
#: Test modules that need rclpy to be imported at all (they import it, piezo_stage's nodes or
#: piezo_stage.cli at the top) or to run (they start ROS processes). Where rclpy does not import
#: (outside the environment of scripts/env.sh) each is reported skipped, whole, without being
#: imported, so their imports stay at the top of the file. A module added here must exist
#: (checked at start, so that a renamed file is not silently dropped).
NEEDS_RCLPY = frozenset(
    {
        "test_bag_play.py",
        "test_demo.py",
        "test_emulated_rig_graph.py",
        "test_emulated_rig_tracking.py",
        "test_env_messages.py",
        "test_experiment_harness.py",
        "test_gcs_sensor.py",
        "test_identifier_cycles.py",
        "test_launch_run.py",
        "test_node_controller.py",
        "test_node_excitation.py",
        "test_node_executor.py",
        "test_node_identifier.py",
        "test_node_live_view.py",
        "test_node_parameters.py",
        "test_node_plant.py",
        "test_node_rig_driver.py",
        "test_node_rig_loop.py",
        "test_node_rig_reader.py",
        "test_node_runtime.py",
        "test_param_docs.py",
        "test_player_cli.py",
        "test_player_node.py",
        "test_recorder_cli.py",
        "test_recorder_lifecycle.py",
        "test_recorder_node.py",
        "test_recorder_units.py",
        "test_replay_identification.py",
    }
)
TEST_DIR = Path(__file__).resolve().parent


def _check_needs_rclpy() -> None:
    unknown = sorted(name for name in NEEDS_RCLPY if not (TEST_DIR / name).is_file())
    if unknown:
        raise pytest.UsageError("conftest.NEEDS_RCLPY names no test file: " + ", ".join(unknown))


@functools.cache
def _rclpy_missing() -> str | None:
    """Why rclpy does not import here, or None when it does. As ``pytest.importorskip`` judges
    it: only a missing module skips; one that is there but fails to import fails the collection
    with its own error."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ImportWarnings of a same-named directory
        try:
            importlib.import_module("rclpy")
        except ModuleNotFoundError as exc:
            return str(exc)
    return None


class _WithoutRclpy(pytest.Module):
    """A module of NEEDS_RCLPY where rclpy does not import: reported skipped, never imported."""


def pytest_pycollect_makemodule(
    module_path: Path, parent: pytest.Collector
) -> pytest.Module | None:
    if module_path.name in NEEDS_RCLPY and _rclpy_missing() is not None:
        return _WithoutRclpy.from_parent(parent, path=module_path)
    return None


@pytest.hookimpl(tryfirst=True)
def pytest_make_collect_report(collector: pytest.Collector) -> pytest.CollectReport | None:
    if not isinstance(collector, _WithoutRclpy):
        return None
    reason = (
        f"Skipped: needs rclpy, which does not import here ({_rclpy_missing()}): "
        "run inside the environment of scripts/env.sh"
    )
    # located at the module (no line: nothing in it ran), not at this conftest
    return pytest.CollectReport(
        collector.nodeid, "skipped", (str(collector.path), None, reason), []
    )


class _NotInUnitLayer(RuntimeError):
    pass


@contextmanager
def _unit_layer_guard(item: pytest.Item) -> Iterator[None]:
    """The unit layer means no sockets, ptys, child processes or DDS: a test marked `unit` that
    opens one (in the test or in any fixture it sets up) fails, and belongs in the `ros` layer."""
    if item.get_closest_marker("unit") is None:
        yield
        return
    import pty
    import socket
    import subprocess

    def refuse(what: str):
        def _refuse(*args, **kwargs):
            raise _NotInUnitLayer(f"{what} in a test marked unit: mark it ros")

        return _refuse

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(socket, "socket", refuse("socket.socket"))
        mp.setattr(subprocess, "Popen", refuse("subprocess.Popen"))
        mp.setattr(pty, "openpty", refuse("pty.openpty"))
        mp.setattr(os, "openpty", refuse("os.openpty"))
        mp.setattr(os, "fork", refuse("os.fork"))
        if _importable("rclpy"):
            import rclpy

            mp.setattr(rclpy, "init", refuse("rclpy.init"))
        yield


# --- real-time tests need a host that can run a loop in real time ----------------------------
#: CPU per sample [µs] of bench/control_loop.py's ``minimal`` loop at 1 kHz (pty -> parse ->
#: law -> TCP, one Python thread) on the development host, where the figures of the
#: ``realtime`` tests were set (README, "the rig's loop")
MINIMAL_LOOP_US = 25.0
#: how many times slower a host may be and still hold them
REALTIME_SLOWDOWN = 2.5
#: set to 1 to run the real-time tests on any host
REALTIME_ANY_HOST = "PIEZO_REALTIME_ANY_HOST"
#: cores a real-time test's processes need idle (emulators, driver, reader, loop): beside a
#: busy process a 2-core host has one, and its graphs fall behind real time
REALTIME_FREE_CORES = 1.5


def _cpu_jiffies() -> tuple[int, int, int] | None:
    """Idle and total jiffies of every CPU together, and how many CPUs, from /proc/stat (None:
    no such file)."""
    try:
        lines = Path("/proc/stat").read_text().splitlines()
    except OSError:
        return None
    v = [int(x) for x in lines[0].split()[1:9]]  # user .. steal (guest is within user)
    cpus = sum(1 for line in lines[1:] if line.startswith("cpu"))
    return v[3] + v[4], sum(v), cpus


def free_cores(seconds: float = 1.0) -> float:
    """Cores the host left idle over the next ``seconds`` (inf where /proc/stat is missing)."""
    before = _cpu_jiffies()
    time.sleep(seconds)
    after = _cpu_jiffies()
    if before is None or after is None or after[1] <= before[1]:
        return float("inf")
    return after[2] * (after[0] - before[0]) / (after[1] - before[1])


@functools.cache
def _minimal_loop_us() -> float:
    """This host's CPU per sample of the minimal loop [µs], measured once (3 s)."""
    sys.path.insert(0, str(ROOT / "bench"))
    import control_loop

    return control_loop.measure("minimal", 1000.0, 3.0).cpu_per_sample * 1e6


def _realtime_host(item: pytest.Item) -> None:
    """Skip a ``realtime`` test, saying why, on a host too slow for a 1 kHz loop in real time:
    its figures (a set point held, a triangle learned to 0.5 %, a commissioning run) are then
    not reached for a physical reason, which this measurement states. A test whose figure needs
    a faster host says so: ``@pytest.mark.realtime(slowdown=1.5)``."""
    marker = item.get_closest_marker("realtime")
    if marker is None:
        return
    reason = too_slow_for_realtime(float(marker.kwargs.get("slowdown", REALTIME_SLOWDOWN)))
    if reason:
        pytest.skip(reason)


def too_slow_for_realtime(slowdown: float = REALTIME_SLOWDOWN) -> str | None:
    """Why this host cannot hold the real-time figures now (None: it can, or
    ``PIEZO_REALTIME_ANY_HOST=1``): the cores other work leaves idle (:func:`free_cores`),
    then the measurement of :func:`_minimal_loop_us`."""
    if os.environ.get(REALTIME_ANY_HOST) == "1":
        return None
    free = free_cores()
    if free < REALTIME_FREE_CORES:
        return (
            f"this host has {free:.1f} cores idle (fewer than {REALTIME_FREE_CORES:g}): "
            f"too loaded for this real-time test ({REALTIME_ANY_HOST}=1 runs it anyway)"
        )
    us = _minimal_loop_us()
    if us <= MINIMAL_LOOP_US * slowdown:
        return None
    return (
        f"this host runs the minimal 1 kHz loop at {us:.0f} us of CPU per sample, "
        f"{us / MINIMAL_LOOP_US:.1f}x the development host's {MINIMAL_LOOP_US:g} us "
        f"(more than {slowdown:g}x): too slow for this real-time test "
        f"({REALTIME_ANY_HOST}=1 runs it anyway)"
    )


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item: pytest.Item):
    _realtime_host(item)
    with _unit_layer_guard(item):
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    with _unit_layer_guard(item):
        yield


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


# --- the DDS probe node ------------------------------------------------------------------------
@pytest.fixture()
def node(request: pytest.FixtureRequest):
    """An rclpy node named `probe` in the test module's namespace (its `NS`, default "/"), with
    rclpy initialised around it: the test's side of a conversation with the nodes under test."""
    from ros_support import probe_node

    with probe_node(getattr(request.module, "NS", "/")) as n:
        yield n


@pytest.fixture()
def probe(node):
    """The same probe node, under the name the rig tests use."""
    return node
