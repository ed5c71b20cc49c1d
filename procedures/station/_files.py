"""Reading an operator's input files without trusting them: regular files only, bounded size, UTF-8.

A FIFO, a device (``/dev/zero``) or a folder given where a file is expected would block a read or
never end; a huge file would eat the machine. Each is refused with one line before it is read.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

MAX_TEXT_BYTES = 4 * 1024 * 1024
"""Largest station, procedure or calibration record file read (the shipped ones are a few kB)."""


class InputRefused(ValueError):
    """An input file that is not read: the message is one line naming the file and why."""


def read_text_file(path: str | Path, *, max_bytes: int = MAX_TEXT_BYTES, what: str = "file") -> str:
    """The text of the regular file ``path``, at most ``max_bytes``, decoded as UTF-8.

    Raises
    ------
    InputRefused
        Not a regular file (folder, FIFO, device, socket), missing, unreadable, too large, or not UTF-8.
    """
    name = str(path)
    try:
        # O_NONBLOCK: opening a FIFO with no writer must not block; it is refused just below.
        fd = os.open(name, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except IsADirectoryError:
        raise InputRefused(f"{name}: is a folder, not a {what}") from None
    except OSError as exc:
        raise InputRefused(f"{name}: cannot read {what}: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise InputRefused(f"{name}: is a folder, not a {what}")
        if not stat.S_ISREG(info.st_mode):
            raise InputRefused(f"{name}: is not a regular file (a FIFO, device or socket); give a {what}")
        if info.st_size > max_bytes:
            raise InputRefused(f"{name}: {info.st_size} bytes; a {what} may have at most {max_bytes} bytes")
        data = b""
        while len(data) <= max_bytes:  # read to the end, but never past the limit (the file may grow)
            chunk = os.read(fd, max_bytes + 1 - len(data))
            if not chunk:
                break
            data += chunk
        if len(data) > max_bytes:
            raise InputRefused(f"{name}: more than {max_bytes} bytes; a {what} may have at most {max_bytes} bytes")
    except OSError as exc:
        raise InputRefused(f"{name}: cannot read {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    return decode_utf8(data, name)


def decode_utf8(data: bytes, name: str) -> str:
    """``data`` as UTF-8 text (a leading byte-order mark dropped), or one line saying where it is not."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise InputRefused(f"{name}:{line}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}); "
                           "save the file as UTF-8") from None
