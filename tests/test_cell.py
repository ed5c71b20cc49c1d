"""The whole simulated cell: up and down repeatedly without leaks, `instrument sim` in the
foreground with a clean stop on SIGTERM, and `instrument run --station sim`."""

from __future__ import annotations

import inspect
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import yaml
from pymodbus.client import ModbusTcpClient

from procedures.cli import main
from sim_devices.cell import UR_PORTS, CellHost, CellNotRunning, SimCell
from sim_devices.control import ControlClient, ControlError

pytestmark = pytest.mark.slow


def _listening(host: str, port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(1.0)
        return probe.connect_ex((host, port)) == 0


def _endpoints_in_use(endpoints: dict) -> list[tuple[str, int]]:
    robot = endpoints["robot"]
    return ([(robot["host"], port) for port in UR_PORTS]
            + [("127.0.0.1", endpoints["rotary_table"]["modbus_tcp_port"]),
               ("127.0.0.1", endpoints["interferometer"]["socketcand"]["port"]),
               (endpoints["control"]["host"], endpoints["control"]["port"])])


def test_cell_up_and_down_three_times_leaks_nothing(tmp_path):
    me = psutil.Process()
    fds_before = me.num_fds()
    children_before = {p.pid for p in me.children(recursive=True)}
    example = yaml.safe_load((Path(__file__).resolve().parents[1] / "sim_devices" / "cell.example.yaml").read_text())
    for seed in range(3):
        config = {k: v for k, v in example.items() if k not in ("seed", "time_scale")} if seed == 2 else None
        with SimCell(seed=seed, directory=tmp_path / f"cell{seed}", config=config) as cell:
            station = yaml.safe_load(cell.station_path.read_text())
            assert station["simulation"]["seed"] == seed
            assert cell.control("ping") == "pong"
            assert cell.client().call("ping") == "pong"  # the same API over loopback TCP
            used = _endpoints_in_use(cell.endpoints)
            assert all(_listening(host, port) for host, port in used)
            ptys = [cell.endpoints["rotary_table"]["modbus_rtu_port"], cell.endpoints["rotary_table"]["gcs_port"],
                    cell.endpoints["interferometer"]["slcan"]["port"]]
            assert all(Path(p).exists() for p in ptys)
            assert all(host.startswith("127.") for host, _ in used)
        assert not [hp for hp in used if _listening(*hp)], "a port stayed open after the cell stopped"
        assert not [p for p in ptys if Path(p).is_symlink() and Path(p).exists()], "a pty link outlived the cell"
    leftover = [p for p in me.children(recursive=True) if p.pid not in children_before and p.is_running()
                and p.status() != psutil.STATUS_ZOMBIE]
    # multiprocessing's resource tracker starts with the first spawn child and serves this process
    # for its lifetime (one, however many cells); anything else is a leak.
    leaked = [p.cmdline() for p in leftover if "multiprocessing.resource_tracker" not in " ".join(p.cmdline())]
    assert not leaked
    assert me.num_fds() <= fds_before + 3


def test_instrument_sim_runs_in_the_foreground_and_stops_on_sigterm(tmp_path):
    process = subprocess.Popen(
        [sys.executable, "-m", "procedures.cli", "sim", "--json", "--seed", "4", "--directory", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1],
    )
    try:
        first_line: list[str] = []
        reader = threading.Thread(target=lambda: first_line.append(process.stdout.readline()), daemon=True)
        reader.start()
        reader.join(90)
        assert first_line and first_line[0].strip(), f"no endpoints printed; stderr: {process.stderr.read()}"
        endpoints = json.loads(first_line[0])
        assert Path(endpoints["station"]).is_file()
        control = endpoints["control"]
        assert ControlClient(control["host"], control["port"], timeout=10).call("ping") == "pong"
        used = _endpoints_in_use(endpoints)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 0
        assert not [hp for hp in used if _listening(*hp)]
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
        process.stdout.close()
        process.stderr.close()


def test_run_with_station_sim_starts_its_own_cell(tmp_path, capsys):
    procedure = tmp_path / "iso.yaml"
    procedure.write_text(yaml.safe_dump({
        "procedure": "iso9283_repeatability", "name": "smoke",
        "parameters": {"cycles": 2, "transform_step": False, "apply_compensation": False,
                       "settle_time_s": 0.05, "frames_per_pose": 1},
    }), encoding="utf-8")
    runs = tmp_path / "runs"
    assert main(["run", str(procedure), "--station", "sim", "--seed", "2", "--runs-dir", str(runs), "--quiet"]) == 0
    run_id, state = capsys.readouterr().out.split()[-2:]
    assert state == "FINISHED"
    assert main(["export", run_id, "--json", "--runs-dir", str(runs)]) == 0
    exported = json.loads(capsys.readouterr().out)
    assert len(exported["samples"]) == 10 and all(s["ok"] for s in exported["samples"])
    assert os.listdir(runs / "sim")  # the cell's directory (frames, truth log) is kept for the report


def test_stop_stops_every_twin_even_when_one_fails(tmp_path):
    stopped, asked = [], []

    class Twin:
        def __init__(self, name, fail=False):
            self.name, self.fail = name, fail

        def request_stop(self):
            asked.append((self.name, len(stopped)))
            if self.fail:
                raise OSError("pipe closed")

        def stop(self):
            stopped.append(self.name)
            if self.fail:
                raise OSError("port busy")

    host = CellHost(str(tmp_path))
    host._started = [("cameras", Twin("cameras")), ("robot", Twin("robot", fail=True)), ("table", Twin("table"))]
    with pytest.raises(RuntimeError, match="stopping failed for robot: OSError: port busy"):
        host.stop()
    assert asked == [("cameras", 0), ("robot", 0), ("table", 0)]  # all told before any is waited for
    assert stopped == ["table", "robot", "cameras"]  # reverse start order, none skipped
    assert not host._started


def test_instrument_sim_reports_a_bad_cell_config_in_one_line(tmp_path, capsys):
    config = tmp_path / "cell.yaml"
    config.write_text("robot:\n  repeatability_std: 1.0e-5\n", encoding="utf-8")
    assert main(["sim", "--config", str(config), "--directory", str(tmp_path / "cell")]) == 2
    err = capsys.readouterr().err
    assert "UR twin config: unknown field(s) ['repeatability_std']" in err and "Traceback" not in err


def test_instrument_sim_reports_an_unknown_cell_section_in_one_line(tmp_path, capsys):
    config = tmp_path / "cell.yaml"
    config.write_text("robto:\n  approach_bias: 1.0e-6\n", encoding="utf-8")
    assert main(["sim", "--config", str(config), "--directory", str(tmp_path / "cell")]) == 2
    err = capsys.readouterr().err
    assert "cell config: unknown field(s) ['robto']" in err and "Traceback" not in err


def test_the_cell_s_twins_are_typed_attributes_only_while_it_runs(tmp_path):
    host = CellHost(str(tmp_path))
    for name in ("world", "robot", "rotary_table", "interferometer", "cameras", "bench"):
        with pytest.raises(CellNotRunning, match="not running"):
            getattr(host, name)
    with pytest.raises(ValueError, match="no twin 'table'; expected one of cameras, robot"):
        host.twin("table")


def test_simcell_offers_the_control_methods_of_cellhost():
    """Every command of the cell's table is a method of both, with the same signature."""
    host = CellHost(".")
    for command, method in host._commands.items():
        name = method.__name__
        assert hasattr(SimCell, name), f"SimCell lacks {name} (command {command!r})"
        assert str(inspect.signature(getattr(SimCell, name))) == str(inspect.signature(getattr(CellHost, name)))


def _read_status(table: dict):
    with ModbusTcpClient(table["host"], port=table["port"], timeout=2.0, retries=0) as modbus:
        assert modbus.connect()
        return modbus.read_holding_registers(1, count=1, device_id=table["unit"])


def test_faults_injected_through_the_control_channel_fire_in_the_running_cell(tmp_path):
    with SimCell(seed=5, directory=tmp_path / "cell") as cell:
        client = cell.client()
        table = yaml.safe_load(cell.station_path.read_text())["devices"]["rotary_table"]
        assert not _read_status(table).isError()

        # The Modbus twin answers the next request with exception 4 (device failure), once.
        assert client.call("inject_fault", device="rotary_table", kind="exception", code=4) == ["exception"]
        refused = _read_status(table)
        assert refused.isError() and refused.exception_code == 4
        assert not _read_status(table).isError()
        assert client.call("fired_faults", device="rotary_table") == [["exception", {"code": 4}]]

        # Forwarding to a twin's own control API (``command`` inside the args used to be a TypeError).
        stats = client.call("device", device="interferometer", command="stats")
        assert client.call("device", device="interferometer", command="arm", kind="drop_reply", frames=7) == [
            "drop_reply"]
        deadline = time.monotonic() + 10.0
        while client.call("device", device="interferometer", command="stats")["dropped"] < stats["dropped"] + 7:
            assert time.monotonic() < deadline, "the armed drop_reply never fired"
            time.sleep(0.05)
        assert cell.fired_faults("interferometer") == [("drop_reply", {"frames": 7})]  # the same, over the pipe
        assert cell.clear_faults("interferometer") == []

        # Clear errors for an unknown command, bad arguments, a twin without faults.
        with pytest.raises(ControlError, match="unknown command 'mount'; expected one of align_interferometer"):
            client.call("mount", axis="x")
        with pytest.raises(ControlError, match=r"bad arguments for mount_on_table\(axis\).*'axis'"):
            client.call("mount_on_table")
        with pytest.raises(ControlError, match="camera file twin takes no faults"):
            client.call("inject_fault", device="cameras", kind="stall")
        with pytest.raises(ControlError, match="unknown fault kind 'jam'"):
            client.call("inject_fault", device="robot", kind="jam")
        assert cell.mount_on_table("y") == "table:y"
        assert cell.mount_on_robot() == "robot"
        assert cell.ping() == "pong"  # the cell is still healthy after all that


# ------------------------------------------------------------------------------ one process per twin
def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _wait_until(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def test_each_twin_runs_in_its_own_process_and_none_outlives_a_killed_supervisor(tmp_path):
    cell = SimCell(seed=6, directory=tmp_path / "cell")
    cell.start()
    try:
        status = cell.status()
        pids = {name: entry["pid"] for name, entry in status.items()}
        assert set(pids) == {"cameras", "robot", "rotary_table", "interferometer"}
        assert all(entry["alive"] for entry in status.values())
        assert len(set(pids.values())) == 4 and cell.supervisor_pid not in pids.values()
        supervisor = psutil.Process(cell.supervisor_pid)
        assert {p.pid for p in supervisor.children()} == set(pids.values())
        robot_host = cell.endpoints["robot"]["host"]
        supervisor.kill()  # SIGKILL: no clean-up code runs in the supervisor
        _wait_until(lambda: all(_gone(pid) for pid in pids.values()), 30.0,
                    f"twins outlived their supervisor: {[n for n, pid in pids.items() if not _gone(pid)]}")
        _wait_until(lambda: not any(_listening(robot_host, port) for port in UR_PORTS), 10.0,
                    "the robot twin's ports stayed open")
    finally:
        cell.stop()


def test_a_twin_that_dies_is_reported_by_name_and_the_others_carry_on(tmp_path):
    with SimCell(seed=7, directory=tmp_path / "cell") as cell:
        robot_pid = cell.status()["robot"]["pid"]
        psutil.Process(robot_pid).kill()
        _wait_until(lambda: not cell.status()["robot"]["alive"], 20.0, "the dead robot twin was not noticed")
        assert cell.status()["robot"]["exitcode"] == -signal.SIGKILL
        with pytest.raises(ControlError, match="the robot twin is not running"):
            cell.client().call("device", device="robot", command="state")
        with pytest.raises(ControlError, match="the robot twin is not running"):
            cell.client().call("inject_fault", device="robot", kind="protective_stop")
        died = cell.truth("twin_died")
        assert [(e["twin"], e["pid"]) for e in died] == [("robot", robot_pid)]
        # The rest of the cell still works: the table, the cameras, the world and its subscribers.
        assert cell.ping() == "pong"
        assert cell.mount_on_table("x") == "table:x"
        assert cell.forward("cameras", "stats")["frames_written"] >= 2
        assert {n for n, e in cell.status().items() if e["alive"]} == {"cameras", "rotary_table", "interferometer"}


def test_instrument_sim_names_a_twin_that_died(tmp_path):
    process = subprocess.Popen(
        [sys.executable, "-m", "procedures.cli", "sim", "--json", "--seed", "8", "--directory", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1],
    )
    try:
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.append(process.stdout.readline()), daemon=True)
        reader.start()
        reader.join(90)
        assert lines and lines[0].strip(), "no endpoints printed"
        control = json.loads(lines[0])["control"]
        client = ControlClient(control["host"], control["port"], timeout=10)
        interferometer_pid = client.call("status")["interferometer"]["pid"]
        psutil.Process(interferometer_pid).kill()
        errors: list[str] = []

        def read_errors():
            for line in process.stderr:
                errors.append(line)

        threading.Thread(target=read_errors, daemon=True).start()
        _wait_until(lambda: any("interferometer twin" in line and "died" in line for line in errors), 20.0,
                    f"no line names the dead twin; stderr: {errors}")
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
        process.stdout.close()


def test_a_blocking_move_returns_once_the_cameras_show_its_final_pose(tmp_path):
    rtde_control = pytest.importorskip("rtde_control")
    with SimCell(seed=9, directory=tmp_path / "cell", time_scale=4.0) as cell:
        host = cell.endpoints["robot"]["host"]
        control = rtde_control.RTDEControlInterface(host)
        try:
            start = control.getForwardKinematics()
            for step in range(6):
                target = [start[0] + 0.004 * (step % 2), start[1], start[2] + 0.003 * (step % 3), *start[3:]]
                assert control.moveL(target, 0.25, 1.2)
                # 'done' came after the attained pose reached every twin: the frames on disk show it.
                frames = cell.truth("frames", last=1)[0]
                pose = cell.truth("pose", last=1)[0]
                assert frames["seq"] == pose["seq"]
                truth = np.asarray(cell.true_opr_in_m())
                np.testing.assert_allclose(frames["opr_in_m"]["t"], truth[:3, 3], atol=1e-12)
            # Every end pose was announced when the move was planned, so the cameras could render it
            # while the arm moved (how many were ready in time depends on the machine's load).
            assert cell.forward("cameras", "stats")["announced"] == 6
        finally:
            control.disconnect()


def test_the_robot_moves_to_another_address_when_its_ports_were_taken_meanwhile(tmp_path, monkeypatch):
    """Another cell may bind the address between the supervisor's check and the robot process's bind."""
    import sim_devices.cell as cell_module

    taken = cell_module.free_loopback_host(first=230, last=240)
    holders = []
    for port in UR_PORTS:
        holder = socket.socket()
        holder.bind((taken, port))
        holder.listen(1)
        holders.append(holder)
    picks: list[str] = []
    real = cell_module.free_loopback_host

    def pick(first: int = 2, last: int = 254, exclude: tuple[str, ...] = ()) -> str:
        picks.append(taken if not picks else real(first=231, last=250, exclude=exclude))
        return picks[-1]

    monkeypatch.setattr(cell_module, "free_loopback_host", pick)
    host = CellHost(str(tmp_path / "cell"), seed=2)
    try:
        endpoints = host.start()
        assert picks[0] == taken and endpoints["robot"]["host"] == picks[-1] != taken
        assert host.status()["robot"]["alive"]
        station = yaml.safe_load(Path(endpoints["station"]).read_text())
        assert station["devices"]["robot"]["host"] == picks[-1]
    finally:
        host.stop()
        for holder in holders:
            holder.close()
