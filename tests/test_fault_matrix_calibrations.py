"""The fault matrix (tests/_fault_matrix.py), its cases on the calibration runs: the rotary table's,
the interferometer's and the starved cameras' faults, each injected mid-run into ``instrument run`` in a
child process."""

from __future__ import annotations

import pytest

from tests._fault_matrix import Case, cases_on, fault_matrix_cell, run_case, write_table

pytestmark = pytest.mark.slow
CASES = cases_on("angle", "displacement", "displacement_1mm")
ROWS: list[dict] = []


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    with fault_matrix_cell(tmp_path_factory.mktemp("cell")) as running:
        yield running
    write_table("calibrations", ROWS)


@pytest.mark.timeout(400)
@pytest.mark.parametrize("case", CASES, ids=[case.name for case in CASES])
def test_fault_mid_run_then_resume_to_finished(cell, tmp_path, case: Case):
    ROWS.extend(run_case(cell, tmp_path, case))
