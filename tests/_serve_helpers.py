"""Processes the serve tests start: ``instrument serve`` and ``instrument run`` as real child processes,
each stopped by the fixture that started it (SIGTERM, then SIGKILL after a bounded wait)."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

SHORT_ISO = """procedure: iso9283_repeatability
name: short ISO for the serve tests
parameters:
  cycles: {cycles}
  settle_time_s: 0.05
  frames_per_pose: 1
  save_frames: {save_frames}
"""


def short_iso(folder: Path, cycles: int = 4, save_frames: str = "always") -> Path:
    """A short ISO 9283 procedure on the simulated cell (5 + 5 × cycles poses)."""
    path = folder / f"iso-{cycles}.yaml"
    path.write_text(SHORT_ISO.format(cycles=cycles, save_frames=save_frames), encoding="utf-8")
    return path


def _lines(stream) -> queue.Queue[str]:
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        for line in stream:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    return lines


def stop(process: subprocess.Popen, timeout: float = 30.0) -> int:
    """SIGTERM, wait up to ``timeout``, then SIGKILL; the exit code."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
    return process.returncode


@contextmanager
def instrument_serve(runs_dir: Path, *extra: str, start_timeout: float = 60.0) -> Iterator[dict[str, str]]:
    """``instrument serve`` on free loopback ports; yields ``{"web": URL, "opcua": URL?, "process": ...}``."""
    command = [sys.executable, "-m", "procedures", "serve", "--runs-dir", str(runs_dir), "--port", "0", *extra]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines = _lines(process.stdout)
        endpoints: dict[str, str] = {}
        deadline = time.monotonic() + start_timeout
        wanted = 2 if "--opcua" in extra else 1
        while len(endpoints) < wanted:
            try:
                line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"instrument serve did not start in {start_timeout} s: "
                                     f"{process.stderr.read() if process.poll() is not None else ''}") from None
            if line.startswith("web view: "):
                endpoints["web"] = line.split(": ", 1)[1].strip()
            elif line.startswith("OPC UA: "):
                endpoints["opcua"] = line.split(": ", 1)[1].strip()
        yield endpoints
    finally:
        code = stop(process)
        assert code == 0, f"instrument serve ended with {code}"


@contextmanager
def instrument_run(runs_dir: Path, procedure: Path, log: Path) -> Iterator[subprocess.Popen]:
    """``instrument run PROCEDURE --station sim --jsonl`` in the background (its output to ``log``)."""
    with open(log, "wb") as out:
        process = subprocess.Popen([sys.executable, "-m", "procedures", "run", str(procedure), "--station", "sim",
                                    "--jsonl", "--runs-dir", str(runs_dir)], stdout=out, stderr=subprocess.STDOUT)
    try:
        yield process
    finally:
        stop(process)
