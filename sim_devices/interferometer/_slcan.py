"""An slcan (Lawicel ASCII) USB-CAN adapter on a pseudo-terminal.

The driver opens ``path``, a symlink to the pty's slave (like a udev ``/dev/serial/by-id/...``
name), so that a simulated unplug/replug (``disconnect``) can hand it a fresh pty at the same path.

Protocol subset (commands end with CR; replies CR = ok, BEL = error):
``O``/``L`` open (normal/listen-only), ``C`` close, ``S0``..``S8`` bitrate, ``V`` version,
``N`` serial number, ``tIIILDD..`` send a standard frame (answered ``z``), an empty command is
answered with CR. While open, every bus frame goes out as ``tIIILDD..\\r``. python-can's client
sends ``C``, ``S8``, an empty line and ``O`` without reading the replies, and ignores them later.

The master end is non-blocking: if the host stops reading and the pty buffer fills, whole frames
are dropped and counted (``overflows``), as a real adapter's FIFO would.

The symlink lives in a temporary folder of its own (``opr-slcan-*``), which ``stop()`` removes. A
process killed with SIGKILL cannot remove it, so the folder carries a lock file that its process
holds locked (``flock``) for as long as it lives; the kernel drops the lock when the process dies,
however it dies, and every new ``SlcanPort`` removes the folders whose lock nobody holds
(``remove_stale_slcan_folders``).
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import shutil
import tempfile
import threading
import time
import tty
from collections.abc import Callable

CommandSink = Callable[[int, bytes], None]

_MAX_PENDING = 64 * 1024  # bytes queued for the host before frames are dropped
SLCAN_FOLDER_PREFIX = "opr-slcan-"
_OWNER_LOCK = "owner.lock"


def remove_stale_slcan_folders(root: str | None = None) -> list[str]:
    """Remove the folders of slcan twins whose process is gone (killed before ``stop()`` ran).

    A folder is stale when the lock file in it can be locked: its owner held it locked while alive.
    Folders being set up (no lock file yet) and live ones are left alone.

    Parameters
    ----------
    root : str, optional
        Where to look (default: the temporary directory).

    Returns
    -------
    list of str
        The folders removed.
    """
    removed = []
    with os.scandir(root or tempfile.gettempdir()) as entries:
        for entry in entries:
            if not entry.name.startswith(SLCAN_FOLDER_PREFIX) or not entry.is_dir(follow_symlinks=False):
                continue
            try:
                fd = os.open(os.path.join(entry.path, _OWNER_LOCK), os.O_RDWR | os.O_CLOEXEC)
            except OSError:
                continue  # no lock file (yet): not ours to judge
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue  # its owner is alive
            shutil.rmtree(entry.path, ignore_errors=True)
            os.close(fd)
            removed.append(entry.path)
    return removed


def _owned_folder() -> tuple[str, int]:
    """A new folder and the fd of its lock file, locked by this process (see the module docstring)."""
    remove_stale_slcan_folders()
    folder = tempfile.mkdtemp(prefix=SLCAN_FOLDER_PREFIX)
    # Locked under another name, then renamed: whoever sees the lock file finds it locked already.
    draft = os.path.join(folder, _OWNER_LOCK + ".new")
    fd = os.open(draft, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    os.rename(draft, os.path.join(folder, _OWNER_LOCK))
    return folder, fd


class SlcanPort:
    def __init__(self, on_command: CommandSink, name: str = "slcan0") -> None:
        self.on_command = on_command
        self._dir, self._owner_lock = _owned_folder()
        self.path = os.path.join(self._dir, name)
        self._lock = threading.Lock()  # guards the pty fds, the output queue and the channel state
        self._master: int | None = None
        self._slave: int | None = None
        self._pending = bytearray()
        self._inbox = bytearray()
        self._channel_open = False
        self._unplugged_until = 0.0
        self._hold_until = 0.0
        self._held = bytearray()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.overflows = 0

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> dict:
        self._plug()
        self._thread = threading.Thread(target=self._serve, name="slcan twin", daemon=True)
        self._thread.start()
        return {"port": self.path}

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        with self._lock:
            self._unplug_locked()
        shutil.rmtree(self._dir, ignore_errors=True)
        if self._owner_lock >= 0:
            os.close(self._owner_lock)
            self._owner_lock = -1

    # ------------------------------------------------------------------------------ the bus side
    def send_frame(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._lock:
            if not (self._channel_open and self._master is not None):
                return
            line = f"t{can_id:03X}{len(data)}{data.hex().upper()}\r".encode("ascii")
            if time.monotonic() < self._hold_until:
                self._held += line
                return
            if self._held:
                line, self._held = bytes(self._held) + line, bytearray()
            self._queue_locked(line, frame=True)

    def hold(self, seconds: float) -> None:
        """Hold every frame for ``seconds``, then send them in one burst (an adapter not polled for
        a while: python-can stamps slcan frames when it reads them, so the pause shows)."""
        with self._lock:
            self._hold_until = max(self._hold_until, time.monotonic() + max(0.0, seconds))

    def send_garbage(self, junk: bytes) -> None:
        with self._lock:
            if self._master is not None:
                self._queue_locked(junk, frame=False)

    def disconnect(self, seconds: float) -> None:
        """Unplug: the pty goes away (the host's reads fail); a new one appears at the same path
        after ``seconds``."""
        with self._lock:
            self._unplug_locked()
            self._unplugged_until = time.monotonic() + max(0.0, seconds)

    # ------------------------------------------------------------------------------ internals
    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation, before the host configures anything
        os.set_blocking(master, False)
        link = self.path + ".new"
        os.symlink(os.ttyname(slave), link)
        os.replace(link, self.path)
        # The twin keeps the slave open too, so the master never sees EIO between host sessions.
        self._master, self._slave = master, slave
        self._channel_open = False
        self._pending.clear()
        self._inbox.clear()
        self._held.clear()

    def _unplug_locked(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None
        self._channel_open = False
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass

    def _queue_locked(self, payload: bytes, frame: bool) -> None:
        if frame and len(self._pending) > _MAX_PENDING:
            self.overflows += 1
            return
        self._pending += payload
        if not frame:  # frames wait for the clock thread's flush() at the end of its batch: one write
            self._flush_locked()

    def flush(self) -> None:
        """Write the frames queued since the last flush to the pty in one write."""
        with self._lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        if not self._pending or self._master is None:
            return
        try:
            written = os.write(self._master, self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EIO):
                return
            raise
        del self._pending[:written]

    def _serve(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                master = self._master
                if master is None and time.monotonic() >= self._unplugged_until:
                    self._plug()
                    master = self._master
                self._flush_locked()
            if master is None:
                self._stop.wait(0.02)
                continue
            try:
                readable, _, _ = select.select([master], [], [], 0.02)
            except (OSError, ValueError):
                continue  # unplugged under us
            if not readable:
                continue
            with self._lock:
                if self._master != master:
                    continue
                try:
                    chunk = os.read(master, 4096)
                except (BlockingIOError, OSError):
                    continue
                self._inbox += chunk
                commands = []
                while (end := self._inbox.find(b"\r")) >= 0:
                    commands.append(bytes(self._inbox[:end]).decode("ascii", "replace"))
                    del self._inbox[: end + 1]
            for command in commands:
                reply = self._handle(command)
                with self._lock:
                    if self._master == master:
                        self._queue_locked(reply, frame=False)

    def _handle(self, command: str) -> bytes:
        if command in ("O", "L"):
            with self._lock:
                self._channel_open = True
            return b"\r"
        if command == "C":
            with self._lock:
                self._channel_open = False
            return b"\r"
        if command == "" or (len(command) == 2 and command[0] == "S" and command[1] in "012345678"):
            return b"\r"
        if command == "V":
            return b"V1013\r"
        if command == "N":
            return b"NIF01\r"
        if command.startswith("t") and len(command) >= 5:
            try:
                can_id, dlc = int(command[1:4], 16), int(command[4])
                data = bytes.fromhex(command[5:])
            except ValueError:
                return b"\a"
            if len(data) != dlc or dlc > 8:
                return b"\a"
            self.on_command(can_id, data)
            return b"z\r"
        return b"\a"
