import os
import signal
import threading

import pytest

from sim_devices import FaultKind, FaultPlan, TwinProcess, TwinProcessError


def test_fault_fires_the_armed_number_of_times():
    plan = FaultPlan()
    plan.arm("drop_reply", count=2)
    plan.arm(FaultKind.DELAY, count=-1, seconds=0.1)
    assert plan.take(FaultKind.GARBAGE) is None
    assert plan.take("drop_reply").kind is FaultKind.DROP_REPLY
    assert plan.take("drop_reply") is not None
    assert plan.take("drop_reply") is None
    for _ in range(5):
        assert plan.take("delay").params == {"seconds": 0.1}
    plan.clear("delay")
    assert plan.take("delay") is None
    assert len(plan.fired()) == 7
    with pytest.raises(ValueError):
        plan.arm("drop_reply", count=0)
    with pytest.raises(ValueError):
        plan.arm("no_such_fault")


def test_twin_process_starts_answers_and_stops():
    with TwinProcess("tests._hosts:EchoHost", {"greeting": "hi"}) as proc:
        assert proc.endpoints["greeting"] == "hi"
        child_pid = proc.call("pid")
        assert child_pid != os.getpid()
        assert proc.call("echo", value=[1, 2]) == [1, 2]
        with pytest.raises(TwinProcessError, match="boom"):
            proc.call("fail")
        assert proc.alive
    assert not proc.alive


def test_twin_start_failure_is_reported():
    with pytest.raises(TwinProcessError, match="refuses to start"):
        TwinProcess("tests._hosts:BrokenHost").start()


def test_an_ended_twin_keeps_its_exit_code_when_another_thread_reaped_it_first():
    """The cell's monitor reads a dead twin's exit code while a status call's ``is_alive()`` may reap
    the child in another thread: the monitor's ``waitpid`` then sees ECHILD. It once stored -1 for a
    twin killed by SIGKILL. Reproduced here exactly: the child is reaped outside multiprocessing and
    its code stored 50 ms later, as the reaping thread does."""
    proc = TwinProcess("tests._hosts:EchoHost", {"greeting": "hi"})
    proc.start()
    try:
        child = proc._process
        assert child is not None and child._popen is not None
        os.kill(child.pid, signal.SIGKILL)
        _, status = os.waitpid(child.pid, 0)  # the other thread's waitpid
        popen = child._popen
        threading.Timer(0.05, lambda: setattr(popen, "returncode", os.waitstatus_to_exitcode(status))).start()
        assert proc.poll_exit(timeout=2.0) == -signal.SIGKILL
    finally:
        proc.stop()
