"""Suite-wide set-up: the order modules run in, which are integration tests, a loopback block per
pytest-xdist worker, and per-test CPU on request.

``make test`` runs the suite on every core (``pytest -n auto --dist loadfile``: a module runs whole
on one worker, so its module-scoped cell is started once). Modules are handed out longest first
(``LONGEST_FIRST``, from measured durations), so the longest never starts last and the workers end
together. ``make test-fast`` leaves out the integration tests (``INTEGRATION``: modules that start
a simulated cell, twin processes, a server, a database or a browser; every ``slow`` test too).

Under ``pytest -n N`` every worker (``gw0``, ``gw1``, …) binds its twins in a 127.0.B block of its
own (``SIM_LOOPBACK_BLOCK``; the UR twin's ports are fixed, so two cells need two addresses), so
workers never compete for an address. Temporary folders are per worker already (pytest's
``tmp_path`` lives under ``basetemp/popen-gwN``), and every cell, twin and server is started and
stopped by a fixture.

The summary ends with a line on this host's speed (best of three short pure-Python and NumPy loops,
timed after the last test): fresh machines of one kind were seen to differ more than twofold, and a
suite's time means little without it.

``SUITE_RESOURCES=FILE`` appends one JSON line per test to FILE: wall and CPU seconds of this process and
of its reaped children, and how its phases ended (a failure is known while the suite still runs), which
shows where the suite's time and CPU go (``SUITE_RESOURCES=/tmp/r.jsonl make test``).
"""

from __future__ import annotations

import json
import os
import resource
import time

import numpy as np
import pytest

from sim_devices.cell import LOOPBACK_BLOCK_ENV

# Module → seconds it took in a full run on the idle 2-core VM; modules not listed take less than ~15 s and
# follow in collection order. Only the order matters: a wrong figure costs balance, not results. The two
# modules that stream a robot in motion with its dense truth (test_dynamic_system, and test_serve_browser's
# pose-stream page) are placed so that they do not run at the same time on the two workers: each is the
# heaviest real-time load of the suite.
LONGEST_FIRST = {
    "test_system_sim.py": 210, "test_dynamic_system.py": 130, "test_fault_matrix_calibrations.py": 120,
    "test_fault_matrix_iso.py": 110,
    "test_kill_resume.py": 86, "test_serve_opcua.py": 77, "test_serve_browser.py": 76, "test_cell.py": 59,
    "test_rotary_drivers.py": 51, "test_results_data.py": 44, "test_cli_interrupts.py": 38,
    "test_robot_isolation.py": 37, "test_fuzz_inputs.py": 34, "test_camera_stream.py": 30, "test_robot_abb.py": 29,
    "test_ur_twin.py": 29, "test_robot_dynamic.py": 23, "test_world_race.py": 19, "test_uncertainty.py": 19,
    "test_uncertainty_coverage.py": 18, "test_dynamic_procedures.py": 18, "test_camera_aravis.py": 18,
    "test_interferometer_can.py": 15, "test_report_pdf.py": 15,
}
# Modules that start a simulated cell, twin processes, a server, a database or a browser.
INTEGRATION = {
    "test_abb_twin.py", "test_robot_abb.py", "test_camera_aravis.py", "test_gige_motion.py",
    "test_gige_pygigevision.py", "test_gige_standalone.py", "test_gige_stream.py",
    "test_camera_stream.py", "test_cell.py", "test_cli_interrupts.py", "test_cli_run_output.py",
    "test_opcua_docs.py", "test_device_settings.py",
    "test_dynamic_procedures.py", "test_dynamic_system.py", "test_fault_matrix_calibrations.py",
    "test_fault_matrix_iso.py", "test_faults_and_process.py",
    "test_fuzz_inputs.py", "test_interferometer_can.py", "test_interferometer_timing.py", "test_kill_resume.py",
    "test_procedures_hostile_inputs.py", "test_pty_relay.py", "test_robot_dynamic.py", "test_robot_isolation.py",
    "test_robot_ur.py", "test_rotary_drivers.py", "test_rotary_modbus.py", "test_rotary_pipython.py",
    "test_run_lock.py", "test_serve_browser.py", "test_serve_opcua.py", "test_serve_shutdown.py",
    "test_store_postgres.py",
    "test_system_sim.py", "test_ur_twin.py", "test_wire_conventions.py", "test_world.py", "test_world_race.py",
}
FIRST_WORKER_BLOCK = 10  # 127.0.10, 127.0.11, …: clear of the 127.0.0 block a developer's own cell uses


def _worker_index() -> int | None:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw3" in a worker, unset otherwise
    return int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else None


def pytest_configure(config: pytest.Config) -> None:
    # Output cut to the terminal's width must not depend on where the suite runs (a developer's
    # narrow terminal, or xdist's workers, which get COLUMNS=80): every test and the processes it
    # starts see a 200-column terminal unless it asks for another.
    os.environ["COLUMNS"] = "200"
    index = _worker_index()
    if index is not None:
        base = os.environ.get(LOOPBACK_BLOCK_ENV, "127.0.0").split(".")
        third = int(base[2]) if len(base) == 3 and base[2].isdigit() else 0
        os.environ[LOOPBACK_BLOCK_ENV] = f"127.0.{third + FIRST_WORKER_BLOCK + index}"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    integration = pytest.mark.integration
    for item in items:
        if item.path.name in INTEGRATION or item.get_closest_marker("slow"):
            item.add_marker(integration)
    # A stable sort: within a module, and among the short modules, collection order stays.
    items.sort(key=lambda item: -LONGEST_FIRST.get(item.path.name, 0))


def _cpu_seconds() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


_OUTCOMES = pytest.StashKey[list[str]]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    outcome = yield
    report = outcome.get_result()
    if report.failed or report.when == "call" or report.skipped:
        item.stash.setdefault(_OUTCOMES, []).append(f"{report.when} {report.outcome}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    path = os.environ.get("SUITE_RESOURCES")
    if not path:
        yield
        return
    wall, (own, children) = time.monotonic(), _cpu_seconds()
    yield
    own_after, children_after = _cpu_seconds()
    record = {"test": item.nodeid, "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
              "wall": round(time.monotonic() - wall, 3), "cpu_self": round(own_after - own, 3),
              "cpu_children": round(children_after - children, 3),
              "outcome": ", ".join(item.stash.get(_OUTCOMES, []))}
    with open(path, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(record) + "\n")


def host_speed() -> tuple[float, float]:
    """Best of three: ms for a 10⁶-step pure-Python loop, and for sorting and transforming 10⁶ floats."""
    data = np.random.default_rng(0).random(1_000_000)
    python_s = numpy_s = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        total = 0
        for i in range(1_000_000):
            total += i * i
        python_s = min(python_s, time.perf_counter() - start)
        start = time.perf_counter()
        np.fft.rfft(np.sort(data))
        numpy_s = min(numpy_s, time.perf_counter() - start)
    return python_s * 1e3, numpy_s * 1e3


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    if _worker_index() is not None:
        return
    python_ms, numpy_ms = host_speed()
    cpus = len(os.sched_getaffinity(0))
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    terminalreporter.write_line(f"host speed after the suite: pure-Python loop {python_ms:.0f} ms, NumPy "
                                f"{numpy_ms:.0f} ms (this VM on 2026-12-03: 44 and 26 ms), {cpus} CPUs, "
                                f"load average {load}")
