"""The generic pty relay: bytes pass, faults hit one reply each, nothing leaks."""

import os
import select
import threading
import time

import serial

from sim_devices import FaultPlan, TwinProcess
from sim_devices._pty import PtyRelay, line_framer


def _echo_device(path, stop):
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        while not stop.is_set():
            if select.select([fd], [], [], 0.05)[0]:
                data = os.read(fd, 1024)
                os.write(fd, data.upper())
    finally:
        os.close(fd)


def test_relay_passes_bytes_and_applies_each_fault_once():
    before = len(os.listdir("/proc/self/fd"))
    faults = FaultPlan()
    relay = PtyRelay(faults, framer=line_framer).start()
    stop = threading.Event()
    device = threading.Thread(target=_echo_device, args=(relay.device_path, stop))
    device.start()
    port = serial.Serial(relay.host_path, timeout=0.3)
    try:
        def ask(text):
            port.reset_input_buffer()
            port.write(text)
            answer = port.read_until(b"\n")
            while answer.endswith(b" \n"):
                answer += port.read_until(b"\n")
            return answer

        assert ask(b"pos?\n") == b"POS?\n"
        assert ask(b"a \nb\n") == b"A \nB\n"  # a multi-line answer is one reply
        faults.arm("drop_reply")
        assert ask(b"x\n") == b""
        faults.arm("truncate")
        assert ask(b"hello\n") == b"HEL"
        faults.arm("garbage", size=4)
        answer = ask(b"ok\n")
        assert answer.endswith(b"OK\n") and len(answer) == 7 and all(b >= 0x80 for b in answer[:4])
        faults.arm("delay", seconds=0.5)
        assert ask(b"late\n") == b""
        time.sleep(0.4)
        assert port.in_waiting == len(b"LATE\n")  # the stale answer a driver must flush
        faults.arm("disconnect", seconds=0.4)
        assert ask(b"a\n") == b"" and ask(b"b\n") == b""
        time.sleep(0.4)
        assert ask(b"back\n") == b"BACK\n"
        assert [k.value for k, _ in faults.fired()] == ["drop_reply", "truncate", "garbage", "delay", "disconnect"]
    finally:
        port.close()
        stop.set()
        device.join()
        relay.stop()
    assert len(os.listdir("/proc/self/fd")) == before


def test_rotary_twin_runs_in_a_twin_process():
    with TwinProcess("sim_devices.rotary_table:make_host",
                     {"config": {"transports": ["gcs"], "table": {"home_speed": 3.0}}, "mount": "z"}) as proc:
        path = proc.endpoints["gcs_port"]
        with serial.Serial(path, timeout=1.0) as port:
            port.write(b"CSV?\n")
            assert port.read_until(b"\n") == b"2.0\n"
            port.write(b"SVO 1 1\nFRF 1\n")  # powered on with the servo off and unreferenced
            time.sleep(1.0)
            port.write(b"MOV 1 10\n")
            time.sleep(1.0)
            port.write(b"ERR?\nPOS? 1\n")
            assert port.read_until(b"\n") == b"0\n"
            reported = float(port.read_until(b"\n").decode().split("=")[1])
        truth = proc.call("truth")
        assert truth["settled"] and truth["homed"]
        assert abs(reported - 10.0) < 1e-3
        assert abs(reported / 180 * 3.141592653589793 - truth["true_angle"]) <= truth["error_bound"] * 2
        proc.call("arm", transport="gcs", kind="drop_reply")
        assert proc.call("fired", transport="gcs") == []
