"""Ctrl-C at any moment from process start is clean: never a traceback, never 'Exception ignored in atexit'.

Each test starts a real ``instrument run … --station sim`` (or ``python -m procedures.demo``) in a process
group of its own and sends SIGINT to that group, as a terminal's Ctrl-C does: while the command line loads,
while the simulated cell starts, while the run runs (it pauses and says how to continue), twice (it aborts)
and as a storm of presses until the process ends. The fixture always stops the group it started (by its id).
The moments are stimuli, not assertions: whatever the moment, the outcome must be one of the clean ones.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCRIPT = Path(sys.executable).with_name("instrument")
UNCLEAN = ("Traceback", "Exception ignored", "KeyboardInterrupt")


class Command:
    """One command in a process group of its own, its output in files (read while it runs).

    It starts as a terminal's foreground job does, with SIGINT at its default, whatever this test process
    inherited (a suite started by a script in the background has SIGINT ignored, and an ignore is inherited
    through exec); ``sigint_ignored`` starts it as such a background job instead. The disposition is set in
    the main thread around the fork only (exec resets a handled signal to its default, keeps an ignored one).
    """

    def __init__(self, tmp_path: Path, argv: list[str], sigint_ignored: bool = False) -> None:
        self.out, self.err = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
        env = {**os.environ, "COLUMNS": "200"}
        for name in ("INSTRUMENT_STORE", "INSTRUMENT_RUNS"):  # every command names its runs folder
            env.pop(name, None)
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN if sigint_ignored else signal.default_int_handler)
        try:
            with open(self.out, "w") as out, open(self.err, "w") as err:
                self.process = subprocess.Popen(argv, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, stdout=out,
                                                stderr=err, start_new_session=True)
        finally:
            signal.signal(signal.SIGINT, previous)

    def catches_sigint(self) -> bool:
        """Whether the process has a handler for SIGINT now (Linux: its ``SigCgt`` mask)."""
        try:
            status = Path(f"/proc/{self.process.pid}/status").read_text()
        except OSError:
            return False
        caught = re.search(r"^SigCgt:\s*([0-9a-f]+)", status, re.M)
        return bool(caught and int(caught.group(1), 16) & (1 << (signal.SIGINT - 1)))

    def ctrl_c(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGINT)

    def wait_for(self, text: str, timeout: float = 150.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.process.poll() is None:
            if text in self.stderr or text in self.stdout:
                return True
            time.sleep(0.05)
        return text in self.stderr or text in self.stdout

    def wait(self, timeout: float = 180.0) -> int:
        return self.process.wait(timeout=timeout)

    @property
    def stdout(self) -> str:
        return self.out.read_text(errors="replace")

    @property
    def stderr(self) -> str:
        return self.err.read_text(errors="replace")

    def stop(self) -> None:
        if self.process.poll() is None:
            try:
                os.killpg(self.process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.process.wait(timeout=30)


@pytest.fixture
def start(tmp_path):
    started: list[Command] = []

    def _start(*argv: str, sigint_ignored: bool = False) -> Command:
        command = Command(tmp_path, list(argv), sigint_ignored)
        started.append(command)
        return command

    yield _start
    for command in started:
        command.stop()


def _instrument_run(tmp_path: Path, settle_s: float = 0.05) -> list[str]:
    head = [str(SCRIPT)] if SCRIPT.exists() else [sys.executable, "-m", "procedures.cli"]
    return [*head, "run", "iso9283_repeatability", "--station", "sim", "--set", "cycles=2", "--set",
            f"settle_time_s={settle_s}", "--set", "frames_per_pose=1", "--runs-dir", str(tmp_path / "runs")]


def _clean(command: Command) -> None:
    for text in (command.stderr, command.stdout):
        assert not any(word in text for word in UNCLEAN), text


def _paused_says_how_to_continue(command: Command, runs: Path) -> None:
    match = re.search(r"left paused; continue with: instrument resume ([0-9a-f]{32}) --runs-dir (\S+)",
                      command.stdout)
    assert match, command.stdout + command.stderr
    assert match.group(2) == str(runs)


@pytest.mark.parametrize("delay_s", [0.4, 1.5, 3.0])
def test_ctrl_c_while_starting_is_one_line(tmp_path, start, delay_s):
    """While the command line loads, the procedure is checked or the simulated cell starts: ``interrupted``
    (or, if the run had already begun, a pause); no twin is left running."""
    command = start(*_instrument_run(tmp_path))
    time.sleep(delay_s)
    command.ctrl_c()
    code = command.wait()
    _clean(command)
    assert code in (130, 3, -signal.SIGINT), (code, command.stderr)
    if code == 130:
        assert command.stderr.strip().splitlines()[-1] == "interrupted"
    if code == 3:
        _paused_says_how_to_continue(command, tmp_path / "runs")


def test_ctrl_c_reaches_a_command_its_shell_started_with_sigint_ignored(tmp_path, start):
    """A script's background job (``instrument serve &``, and the runs it launches) inherits SIGINT ignored;
    the command takes it back as it starts, so that a Ctrl-C (or the web view's Pause) while it loads is
    the one line ``interrupted``, not lost. Before, it was ignored until the run began: the run then ran
    to its end, exit 0."""
    command = start(*_instrument_run(tmp_path), sigint_ignored=True)
    deadline = time.monotonic() + 60
    while not command.catches_sigint() and command.process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert command.catches_sigint(), "the command never took SIGINT"
    command.ctrl_c()
    code = command.wait()
    _clean(command)
    assert code == 130, (code, command.stderr)
    assert command.stderr.strip().splitlines()[-1] == "interrupted"


def test_one_ctrl_c_pauses_and_says_how_to_continue(tmp_path, start):
    command = start(*_instrument_run(tmp_path))
    assert command.wait_for("dry run:"), command.stderr  # the run has started
    time.sleep(0.5)
    command.ctrl_c()
    assert command.wait() == 3
    _clean(command)
    assert "Ctrl-C: pausing at the next safe point (Ctrl-C again aborts)" in command.stderr
    _paused_says_how_to_continue(command, tmp_path / "runs")


def test_a_second_ctrl_c_aborts(tmp_path, start):
    """Each pose settles 5 s: the second press comes well before the next safe point."""
    command = start(*_instrument_run(tmp_path, settle_s=5.0))
    assert command.wait_for("dry run:"), command.stderr
    time.sleep(1.0)
    command.ctrl_c()
    assert command.wait_for("Ctrl-C: pausing")
    time.sleep(0.2)
    command.ctrl_c()
    assert command.wait() == 2, command.stdout + command.stderr
    _clean(command)
    assert "ABORTED" in command.stdout + command.stderr and "aborted by a second Ctrl-C" in command.stdout


def test_a_storm_of_ctrl_c_ends_cleanly(tmp_path, start):
    """Ctrl-C pressed again and again from the first second until the process has gone (its report, its
    shutdown and the cell's included)."""
    command = start(*_instrument_run(tmp_path))
    time.sleep(1.0)
    deadline = time.monotonic() + 150
    while command.process.poll() is None and time.monotonic() < deadline:
        command.ctrl_c()
        time.sleep(0.3)
    code = command.wait()
    _clean(command)
    assert code in (130, 2, 3), (code, command.stderr)


def test_the_demo_pauses_on_one_ctrl_c_like_run(tmp_path, start):
    runs = tmp_path / "runs"
    command = start(sys.executable, "-m", "procedures.demo", "--quick", "--cycles", "2", "--quiet",
                    "--runs-dir", str(runs))
    assert command.wait_for("== 1/3 displacement_calibration: run"), command.stderr
    time.sleep(1.0)
    command.ctrl_c()
    assert command.wait() == 3
    _clean(command)
    assert "PAUSED" in command.stderr and "ABORTED" not in command.stderr
    match = re.search(r"demo: displacement_calibration left paused; continue it with: instrument resume "
                      r"([0-9a-f]{32}) --runs-dir (\S+)", command.stderr)
    assert match and match.group(2) == str(runs), command.stderr
