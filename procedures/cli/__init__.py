"""The terminal face: the ``instrument`` command line.

What it offers: ``main(argv)`` (the ``instrument`` script's entry point, ``procedures.cli:main``; also
``python -m procedures.cli``), ``build_parser()``, the error log's name (``ERROR_LOG``), and the pieces a
run's terminal session is made of: ``drive`` (a run or resume from start to its last line), the live
``Display``, the pause prompt (``ask_pause_key``, ``console_pause_handler``), the signal handling
(``signals_control``, ``detach_at_once``), the command that continues a paused run (``resume_command``),
where ``--station sim`` cells live (``cell_directory``), how ``instrument sim`` lists a cell's endpoints
(``endpoint_lines``) and what ``instrument locate`` decodes (``MAX_IMAGE_PIXELS``, checked against the size an
image file's header declares: ``declared_image_size``).

One module per command (``_run``, ``_resume``, ``_runs``, ``_show``, ``_history``, ``_report``,
``_export``, ``_validate``, ``_locate``, ``_sim``, ``_serve``), with what they share in ``_common`` and the
progress display in ``_display``. It stands on the engine, the report and the store (and below); the
``serve`` command starts the web face (``procedures.serve``), which never imports this package.

Every command module imports at its top only what its parser needs; the stacks a command stands on (the
engine, the report, the measurement core, the display) load when it runs, so that ``--version``, ``--help``
and the reading commands start at once (``tests/test_cli_startup.py``).
"""

from __future__ import annotations

import importlib
import signal
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from procedures.cli._common import (
        ask_pause_key,
        cell_directory,
        console_pause_handler,
        detach_at_once,
        drive,
        resume_command,
        signals_control,
    )
    from procedures.cli._display import Display
    from procedures.cli._locate import MAX_IMAGE_PIXELS, declared_image_size
    from procedures.cli._main import ERROR_LOG, build_parser
    from procedures.cli._sim import endpoint_lines

# Loaded on first use: ``instrument --version`` must not pay for the display (rich) or a run's stack, and the
# ``instrument`` script's own import of ``main`` is over before a Ctrl-C could find Python's traceback.
_LAZY = {**dict.fromkeys(("ask_pause_key", "cell_directory", "console_pause_handler", "detach_at_once", "drive",
                          "resume_command", "signals_control"), "_common"),
         "Display": "_display", "endpoint_lines": "_sim",
         "MAX_IMAGE_PIXELS": "_locate", "declared_image_size": "_locate", "ERROR_LOG": "_main", "build_parser": "_main"}


def _interrupt_in_disguise(exc: BaseException) -> bool:
    """A Ctrl-C that a library turned into an error of its own: raised while pydantic-core builds a model's
    validator (a model class defined during a lazy import), it comes out as ``SchemaError: ... KeyboardInterrupt``;
    elsewhere as an exception whose cause or context is the KeyboardInterrupt."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, KeyboardInterrupt):
            return True
        if type(current).__name__ == "SchemaError" and "KeyboardInterrupt" in str(current):
            return True
        current = current.__cause__ or current.__context__
    return False


def main(argv: list[str] | None = None) -> int:
    """The ``instrument`` command on ``argv`` (default: the process's arguments); returns its exit status.

    Called without ``argv`` (the ``instrument`` script, ``python -m procedures.cli``) it owns the process: a
    Ctrl-C while the command line loads is the one line ``interrupted`` (exit 130), and once the command has
    ended Ctrl-C is ignored, so that the interpreter's shutdown (its atexit callbacks) is never cut short.
    """
    if argv is None:
        _take_ctrl_c()
    try:
        try:
            from procedures.cli._main import main as command

            return command(argv)
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        except Exception as exc:
            if not _interrupt_in_disguise(exc):
                raise
            print("interrupted", file=sys.stderr)
            return 130
    finally:
        if argv is None:
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _take_ctrl_c() -> None:
    """SIGINT raises KeyboardInterrupt in this process from now on, even if it was started with SIGINT
    ignored: a non-interactive shell starts its background jobs so (``instrument serve &`` in a start-up
    script, whose runs inherit it), and Python keeps an inherited ignore. The run itself always takes
    Ctrl-C (``signals_control``) and the web view's Pause is a SIGINT: a press while the command loads
    must not be the one that is silently lost."""
    signal.signal(signal.SIGINT, signal.default_int_handler)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


__all__ = ["ERROR_LOG", "MAX_IMAGE_PIXELS", "Display", "ask_pause_key", "build_parser", "cell_directory",
           "console_pause_handler", "declared_image_size", "detach_at_once", "drive", "endpoint_lines", "main",
           "resume_command", "signals_control"]
