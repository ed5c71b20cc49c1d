"""The demo's own pieces (the procedures it runs are covered by the system tests)."""

import numpy as np

from procedures.demo import ARCSEC, DEMO_PARAMETERS, iso_table, write_procedure
from procedures.engine import load_procedure


def test_demo_procedures_validate_and_keep_the_paper_grids(tmp_path):
    for name, overrides in DEMO_PARAMETERS.items():
        path = write_procedure(name, tmp_path, overrides)
        procedure = load_procedure(path, path.read_text(encoding="utf-8"))
        params = procedure.parameters
        for key, value in overrides.items():
            assert getattr(params, key) == value
        if name == "displacement_calibration":
            assert (params.start_mm, params.stop_mm, params.step_mm, params.repeats, params.groups) == (0, 70, 5, 3, 3)
        if name == "iso9283_repeatability":
            assert params.cycles == 30


def test_iso_table_shows_measured_beside_true_in_report_units():
    stats = {"rp_l": 35.2e-6, "rp_l_ci": [30.1e-6, 44.0e-6], "rp_a": 11 * ARCSEC, "rp_b": 10 * ARCSEC,
             "rp_c": 12 * ARCSEC, "ap_p": 78.6e-6}
    true = {"rp_l": 34.9e-6, "rp_a": 10.5 * ARCSEC, "rp_b": 9.5 * ARCSEC, "rp_c": 12.5 * ARCSEC}
    results = {"order": ["P1"], "points": {"P1": {"stats": stats, "true_stats": true}}}
    row = iso_table(results).splitlines()[-1]
    assert row == "| P1 | 35.20 [30.10, 44.00] | 34.90 | 11.00 / 10.50 | 10.00 / 9.50 | 12.00 / 12.50 | 78.6 |"
    assert np.isclose(ARCSEC, np.radians(1 / 3600))
