"""``instrument serve`` stopped while live pages follow it: SIGTERM (or Ctrl-C) ends every open event
stream and the process exits 0 without a traceback. Before, uvicorn's graceful shutdown waited 2 s
for the streams, which never end by themselves, then cancelled them and logged a ``CancelledError``
traceback for each."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests._serve_helpers import stop

pytestmark = pytest.mark.timeout(120)


def _serve(runs_dir: Path) -> tuple[subprocess.Popen, str, int]:
    process = subprocess.Popen([sys.executable, "-m", "procedures", "serve", "--runs-dir", str(runs_dir),
                                "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert process.stdout is not None
    for line in process.stdout:  # the first line with the address; the pipe ends if the process does
        found = re.search(r"web view: http://([\d.]+):(\d+)/", line)
        if found:
            return process, found.group(1), int(found.group(2))
    stop(process)
    raise AssertionError(f"instrument serve did not start: {process.stderr.read() if process.stderr else ''}")


def _open_stream(host: str, port: int, path: str) -> tuple[socket.socket, bytes]:
    """A live page's event stream, read until its first event or keep-alive has come."""
    connection = socket.create_connection((host, port), timeout=30)
    connection.sendall(f"GET {path} HTTP/1.1\r\nHost: {host}\r\nAccept: text/event-stream\r\n\r\n".encode())
    received = b""
    while b"\r\n\r\n" not in received or not re.search(rb"\r\n\r\n[0-9a-f]+\r\n", received):
        chunk = connection.recv(65536)
        assert chunk, f"{path}: the connection closed before the first event: {received!r}"
        received += chunk
    assert received.startswith(b"HTTP/1.1 200"), received[:200]
    return connection, received


def _read_to_end(connection: socket.socket) -> bytes:
    received = b""
    while chunk := connection.recv(65536):
        received += chunk
    connection.close()
    return received


@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_serve_stops_cleanly_with_live_pages_connected(tmp_path, stop_signal):
    process, host, port = _serve(tmp_path / "runs")
    try:
        streams = [_open_stream(host, port, path) for path in ("/api/changes", "/api/runs/current/stream")]
        process.send_signal(stop_signal)
        started = time.monotonic()
        endings = [received + _read_to_end(connection) for connection, received in streams]
        _, stderr = process.communicate(timeout=60)
        took = time.monotonic() - started
    finally:
        stop(process)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr and "CancelledError" not in stderr, stderr
    for ending in endings:
        # chunked transfer's last chunk: the server ended the stream, it did not cut the connection
        assert ending.endswith(b"0\r\n\r\n"), ending[-200:]
    print(f"stopped in {took:.2f} s")
