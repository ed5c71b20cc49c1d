"""The pause prompt (single keys on a real pseudo-terminal), help on every argument, ``instrument sim``'s text."""

from __future__ import annotations

import argparse
import io
import os
import pty
import termios
import threading
import time

import pytest

from procedures.cli import ask_pause_key, build_parser, endpoint_lines
from procedures.kinds import KINDS


@pytest.fixture
def terminal():
    """A pseudo-terminal pair (the prompt reads the follower end; the test types on the leader)."""
    leader, follower = pty.openpty()
    yield leader, follower
    os.close(leader)
    os.close(follower)


def _ask(follower: int, keys: bytes, leader: int) -> tuple[str | None, str]:
    out = io.StringIO()
    answer: dict[str, str] = {}
    asking = threading.Thread(target=lambda: answer.setdefault("it", ask_pause_key(follower, out)), daemon=True)
    asking.start()
    deadline = time.monotonic() + 20
    while termios.tcgetattr(follower)[3] & termios.ICANON:  # type once the prompt reads single keys
        assert time.monotonic() < deadline, "the prompt never put the terminal in single-key mode"
        time.sleep(0.01)
    for key in keys:  # one key at a time, as typed
        os.write(leader, bytes([key]))
    asking.join(20)
    return answer.get("it"), out.getvalue()


@pytest.mark.parametrize(("keys", "expected"), [(b"q", "detach"), (b"a", "abort"), (b"\r", "resume"),
                                                (b"Q", "detach")])
def test_one_key_answers_without_enter(terminal, keys, expected):
    leader, follower = terminal
    answer, out = _ask(follower, keys, leader)
    assert answer == expected and "not an answer" not in out


def test_an_unknown_key_asks_again_and_the_terminal_mode_is_restored(terminal):
    leader, follower = terminal
    before = termios.tcgetattr(follower)
    answer, out = _ask(follower, b"xz q", leader)
    assert answer == "detach"
    assert out.count("not an answer") == 3 and "\nx: not an answer. run paused: [Enter] resume" in out
    assert termios.tcgetattr(follower) == before  # canonical mode and echo back as they were


def _actions(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from ((name, a) for a in sub._actions)


def test_every_argument_of_every_command_has_help_and_run_lists_its_exit_codes():
    parser = build_parser()
    missing = [f"{name} {action.dest}" for name, action in _actions(parser)
               if action.help is None and not isinstance(action, argparse._HelpAction)]
    assert missing == []
    assert "exit codes:" in parser.format_help() and "3    run/resume: the run was left PAUSED" in parser.format_help()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in subparsers.choices:
        assert "exit codes" in subparsers.choices[name].format_help().lower(), name
    procedure = next(a for a in subparsers.choices["run"]._actions if a.dest == "procedure")
    assert all(name in procedure.help for name in KINDS), procedure.help  # the built-in procedures, by name


def test_sim_prints_endpoints_a_person_reads():
    endpoints = {"robot": {"host": "127.0.0.5", "rtde_port": 30004, "dashboard_port": 29999},
                 "rotary_table": {"modbus_tcp": {"host": "127.0.0.1", "port": 5020}, "rtu": "/dev/pts/4"},
                 "control": {"host": "127.0.0.1", "port": 41234}, "truth_log": "cell/truth.jsonl",
                 "station": "cell/station.yaml"}
    lines = endpoint_lines(endpoints, seed=3, time_scale=4.0)
    assert lines[0] == "simulated cell running (seed 3, time scale 4); Ctrl-C stops it"
    assert lines[1:4] == ["  station file     cell/station.yaml", "  truth log        cell/truth.jsonl",
                          "  control channel  127.0.0.1:41234"]
    assert "  robot            host 127.0.0.5, rtde port 30004, dashboard port 29999" in lines
    assert "  rotary table     modbus tcp 127.0.0.1:5020, rtu /dev/pts/4" in lines
    assert not any(c in "".join(lines) for c in "{}'")  # no Python reprs
