"""``instrument runs`` filters and ``instrument history``: one robot's RP/AP over time, changes flagged.

The stores are built with known figures (the results a run stores), so the flags can be checked
against a change that is known to exceed, or to stay within, the uncertainties.
"""

from __future__ import annotations

import json
import math

import pytest

from instrument import ARCSEC
from procedures.cli import main
from procedures.report import iso_points, iso_rows, point_figure
from procedures.serve import StoreReader
from procedures.store import RunState, RunStore

SERIAL = "20235500777"


def _iso_results(rp_l: float, *, u: float | None = None, ci: float | None = None) -> dict:
    stats = {"rp_l": rp_l, "rp_a": 10 * ARCSEC, "rp_b": 11 * ARCSEC, "rp_c": 12 * ARCSEC, "ap_p": 80e-6}
    if ci is not None:
        stats["rp_l_ci"] = [rp_l - ci, rp_l + ci]
    entry: dict = {"n": 30, "stats": stats}
    if u is not None:  # the shape issue 13 adds: an object per figure
        entry["stats"] = {**stats, "rp_l": {"value": rp_l, "expanded_uncertainty": u, "coverage_factor": 2}}
    return {"kind": "iso9283", "order": ["P1", "P2"], "points": {"P1": entry, "P2": {"n": 30, "stats": dict(stats)}}}


def _add(store: RunStore, results: dict | None, *, serial: str | None = SERIAL, state=RunState.FINISHED,
         reason: str | None = None, procedure: str = "iso9283_repeatability") -> str:
    run_id = store.create_run(procedure=procedure, parameters={}, station={}, software_version="t",
                              station_name="cell 1")
    if serial:
        store.update_run(run_id, robot_manufacturer="Universal Robots", robot_model="UR10e", robot_serial=serial,
                         robot_controller_version="5.15")
    store.set_state(run_id, state, reason=reason)
    if results is not None:
        store.set_results(run_id, results)
    return run_id


@pytest.fixture
def runs_dir(tmp_path):
    with RunStore(tmp_path) as store:
        ids = [
            _add(store, _iso_results(30e-6, u=1e-6)),
            _add(store, _iso_results(30.5e-6, u=1e-6)),  # moved 0.5 µm: within √2 µm
            _add(store, _iso_results(40e-6, u=1.5e-6)),  # moved 9.5 µm: beyond
            _add(store, None, state=RunState.FAILED, reason="robot: moveL failed: the connection was lost\n"
                                                             "  traceback line 2\n  line 3"),
            _add(store, None, serial="OTHER-1", procedure="displacement_calibration"),
            _add(store, None, serial=None, state=RunState.ABORTED, reason="aborted by SIGTERM"),
        ]
    return tmp_path, ids


def test_history_flags_a_change_beyond_the_uncertainties_only(runs_dir, capsys):
    runs, ids = runs_dir
    assert main(["history", "--robot", SERIAL, "--runs-dir", str(runs), "--json"]) == 0
    history = json.loads(capsys.readouterr().out)
    assert history["runs"] == 3 and history["model"] == "UR10e"
    p1 = history["points"]["P1"]
    assert [e["run_id"] for e in p1] == ids[:3]
    assert [e["figures"]["rp_l"]["u"] for e in p1] == [1e-6, 1e-6, 1.5e-6]
    assert [sorted(e["changed"]) for e in p1] == [[], [], ["rp_l"]]
    assert p1[2]["changed"]["rp_l"] == pytest.approx(9.5e-6)
    assert all(not e["changed"] for e in history["points"]["P2"])  # no uncertainty there: nothing to judge by

    assert main(["history", "--robot", SERIAL, "--runs-dir", str(runs)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"Universal Robots UR10e serial {SERIAL}: 3 finished ISO 9283 runs"
    (flagged,) = [line for line in out.splitlines() if line.startswith("20") and "!" in line]
    assert ids[2][:8] in flagged and "40.00 ± 1.50 !" in flagged and "changed: RP_l +9.50 µm" in flagged
    assert "1 point-runs changed beyond their uncertainty" in out


def test_history_of_an_unknown_robot_names_the_known_ones(runs_dir, capsys):
    runs, _ = runs_dir
    for extra in ([], ["--json"]):  # a wrong serial is a wrong input: one line on stderr, exit 1
        assert main(["history", "--robot", "nope", "--runs-dir", str(runs), *extra]) == 1
        out, err = capsys.readouterr()
        assert out == ""
        assert err.splitlines() == [f"no finished ISO 9283 run of robot nope (robots in the store: {SERIAL}, OTHER-1)"]


def test_figures_fall_back_to_the_sampling_interval():
    with_ci = point_figure(_iso_results(30e-6, ci=4e-6)["points"]["P1"], "rp_l")
    assert with_ci["u"] == pytest.approx(4e-6) and with_ci["u_source"] == "ci"
    with_u = point_figure(_iso_results(30e-6, u=1e-6, ci=4e-6)["points"]["P1"], "rp_l")
    assert with_u["u"] == 1e-6 and with_u["u_source"] == "U" and with_u["ci"] == pytest.approx([26e-6, 34e-6])
    assert point_figure({"stats": {"rp_l": math.nan}}, "rp_l") is None
    assert point_figure({"stats": {}}, "rp_a") is None


def test_the_web_views_robot_history_groups_by_serial_and_flags_the_same_change(runs_dir):
    runs, ids = runs_dir
    reader = StoreReader(runs)
    try:
        robots = {r["robot"]["key"] for r in reader.runs()}
        assert robots == {f"serial:{SERIAL}", "serial:OTHER-1", "station:cell 1"}
        history = reader.iso_history(f"serial:{SERIAL}")
        assert [h["run"]["id"] for h in history] == ids[:3]
        assert [h["points"]["P1"]["changed"] for h in history][2]["rp_l"] == pytest.approx(9.5e-6)
        assert history[0]["points"]["P1"]["uncertainty"]["rp_l"] == 1e-6
        assert history[0]["run"]["robot"]["label"] == f"Universal Robots UR10e serial {SERIAL}"
    finally:
        reader.close()


def test_runs_is_an_aligned_table_with_filters(runs_dir, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")  # a wide terminal: the columns, not the cut to an 80-column one
    runs, ids = runs_dir
    assert main(["runs", "--runs-dir", str(runs)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["RUN", "CREATED", "STATE", "SAMPLES", "PROCEDURE", "STATION", "ROBOT", "REASON"]
    assert [line.split()[0] for line in lines[1:]] == [i[:12] for i in ids]
    columns = [lines[0].index(name) for name in ("STATE", "PROCEDURE", "ROBOT")]
    for line in lines[1:]:
        assert all(line[c - 2:c] == "  " for c in columns)  # every column starts where its header does
    failed = lines[4]
    assert failed.endswith("robot: moveL failed: the connection was lost") and "traceback" not in "\n".join(lines)

    def listed(*args: str) -> list[str]:
        assert main(["runs", "--runs-dir", str(runs), *args]) == 0
        return [line.split()[0] for line in capsys.readouterr().out.splitlines()[1:]]

    assert listed("--last", "2") == [i[:12] for i in ids[-2:]]
    assert listed("--state", "failed", "--state", "ABORTED") == [ids[3][:12], ids[5][:12]]
    assert listed("--procedure", "displacement_calibration") == [ids[4][:12]]
    assert listed("--robot", SERIAL, "--state", "FINISHED", "--last", "1") == [ids[2][:12]]
    assert main(["runs", "--runs-dir", str(runs), "--robot", "nobody"]) == 0
    assert capsys.readouterr().out.strip() == "no runs match"


@pytest.mark.parametrize("args", [["--last", "0"], ["--state", "DONE"], ["--last", "x"]])
def test_bad_filters_are_usage_errors(runs_dir, args, capsys):
    runs, _ = runs_dir
    with pytest.raises(SystemExit) as exited:
        main(["runs", "--runs-dir", str(runs), *args])
    assert exited.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_the_reported_figure_objects_win_over_the_raw_statistics():
    """The shape the ISO kind stores (docs/results.md): raw statistics per point, and the reported figure
    objects (noise bias corrected, with U) under ``results["figures"]["points"]``. The end-of-run table, the
    history, the web view and OPC UA must show what the report states."""
    results = _iso_results(38.14e-6, ci=5.3e-6)
    results["figures"] = {"points": {"P1": {"rp_l": {"value": 37.72e-6, "expanded_uncertainty": 1.91e-6,
                                                     "coverage_factor": 2, "confidence_interval": [34e-6, 44.6e-6]},
                                            "rp_a": {"value": 11.8 * ARCSEC, "expanded_uncertainty": 1.5 * ARCSEC}}}}
    p1, p2 = iso_rows(results)
    assert p1["rp_l"]["value"] == 37.72e-6 and p1["rp_l"]["u"] == 1.91e-6 and p1["rp_l"]["u_source"] == "U"
    assert p1["rp_l"]["ci"] == [34e-6, 44.6e-6]
    assert p1["rp_a"]["value"] == pytest.approx(11.8 * ARCSEC) and p1["ap_p"] == {"value": 80e-6, "u": None,
                                                                                  "u_source": None, "ci": None}
    assert p2["rp_l"]["value"] == 38.14e-6 and p2["rp_l"]["u_source"] == "ci"  # no figure objects for P2
    points = iso_points(results)
    assert points["P1"]["rp_l"] == 37.72e-6 and points["P1"]["rp_l_u"] == 1.91e-6
    assert points["P1"]["rp_l_ci"] == pytest.approx([32.84e-6, 43.44e-6])  # the sampling interval stays
    assert "rp_l_u" not in points["P2"] and points["P2"]["rp_l"] == 38.14e-6


def test_history_separates_compensated_from_uncompensated_runs(tmp_path, capsys):
    """An uncompensated run carries the instrument's own systematic error: it is shown apart, and a change
    is judged against the previous run of the same kind only (50 µm uncompensated beside 32 µm compensated
    is no change of the robot)."""
    def results(rp_l: float, records: list[str]) -> dict:
        return {**_iso_results(rp_l, u=1e-6), "compensation": records}

    with RunStore(tmp_path) as store:
        compensated = [_add(store, results(32e-6, ["sha256:d", "sha256:a"])),
                       _add(store, results(32.2e-6, ["sha256:d", "sha256:a"]))]
        uncompensated = [_add(store, results(50e-6, [])), _add(store, results(60e-6, []))]
        _add(store, results(32.1e-6, ["sha256:d", "sha256:a"]))
    assert main(["history", "--robot", SERIAL, "--runs-dir", str(tmp_path)]) == 0
    tables: dict[str, list[list[str]]] = {}
    for block in capsys.readouterr().out.split("\n\n")[1:-1]:
        heading, _, *rows = block.splitlines()
        tables[heading] = [row.split() for row in rows]
    comp = "P1 — compensated (calibration records in force)"
    uncomp = "P1 — uncompensated (no calibration record: the figures include the instrument's own errors)"
    assert list(tables)[:2] == [comp, uncomp]
    assert [row[2] for row in tables[comp]][:2] == [run_id[:8] for run_id in compensated]
    assert [row[2] for row in tables[uncomp]] == [run_id[:8] for run_id in uncompensated]
    assert not any("!" in row for row in tables[comp])  # 32 µm after 60 µm uncompensated: no change flagged
    assert tables[uncomp][0][4:6] == ["50.00", "±"] and "!" not in tables[uncomp][0]
    assert tables[uncomp][1][4:8] == ["60.00", "±", "1.00", "!"]  # 50 → 60 µm, both uncompensated: flagged
    assert main(["history", "--robot", SERIAL, "--runs-dir", str(tmp_path), "--json"]) == 0
    entries = json.loads(capsys.readouterr().out)["points"]["P1"]
    assert [e["compensation"] for e in entries] == ["compensated"] * 2 + ["uncompensated"] * 2 + ["compensated"]
    assert entries[0]["records"] == ["sha256:d", "sha256:a"] and entries[2]["records"] == []
    assert entries[2]["changed"] == {} and entries[4]["changed"] == {}
