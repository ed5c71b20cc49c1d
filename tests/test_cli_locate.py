"""``instrument locate IMAGE... [--json]`` on image files written with cv2.imwrite."""

import json

import cv2
import numpy as np
import pytest

from procedures.cli import main
from tests.synthetic_cross import render_cross


@pytest.fixture
def cross_8bit(tmp_path):
    img, truth = render_cross((240, 320), (171.3, 108.6), 0.12, 0.01, seed=21)
    path = tmp_path / "cross8.png"
    assert cv2.imwrite(str(path), img)
    return path, truth


@pytest.fixture
def cross_12bit(tmp_path):
    img, truth = render_cross((240, 320), (140.8, 131.1), -0.2, dtype=np.uint16, saturation=4095,
                              amplitude=6000.0, background=120.0, noise=30.0, seed=22)
    path = tmp_path / "cross12.png"
    assert cv2.imwrite(str(path), img)
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    return path, truth


def test_json_output_matches_truth(cross_8bit, cross_12bit, capsys):
    (p8, t8), (p12, t12) = cross_8bit, cross_12bit
    assert main(["locate", str(p8), "--json"]) == 0
    assert main(["locate", str(p12), "--json", "--saturation", "4095"]) == 0
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["image"] for r in records] == [str(p8), str(p12)]
    for record, truth in zip(records, (t8, t12)):
        assert "error" not in record
        assert np.hypot(*(np.array(record["center_px"]) - truth.center)) < 0.02
        assert record["angle_rad"] == pytest.approx(truth.angle, abs=2e-4)
        assert record["perpendicularity_rad"] == pytest.approx(truth.perpendicularity, abs=4e-4)
        for key in ("horizontal", "vertical"):
            line = record[key]
            assert line["sections"] > 150 and line["residual_rms_px"] < 0.05
            assert np.linalg.norm(line["direction"]) == pytest.approx(1.0)
    assert records[0]["horizontal"]["saturated_sections"] == 0
    assert records[1]["horizontal"]["saturated_sections"] > 150  # 6000 counts clip at 4095


def test_text_output_one_line_per_image(cross_8bit, capsys):
    path, truth = cross_8bit
    assert main(["locate", str(path), str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"{path}: centre ({truth.center[0]:.2f}")
    assert "angle" in lines[0] and "sections" in lines[0] and "saturated 0/0" in lines[0]


def test_errors_are_reported_per_image(cross_8bit, tmp_path, capsys):
    good, _ = cross_8bit
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((240, 320), 12, np.uint8))
    missing = tmp_path / "missing.png"
    assert main(["locate", str(blank), str(missing), str(good), "--json"]) == 1
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert "no cross" in records[0]["error"]
    assert records[1]["error"] == "cannot read image file"
    assert "error" not in records[2]
    # text mode: errors go to stderr, the good image still prints
    assert main(["locate", str(blank), str(good)]) == 1
    captured = capsys.readouterr()
    assert "no cross" in captured.err and str(good) in captured.out


def test_colour_file_is_read_as_grey(cross_8bit, tmp_path, capsys):
    path, truth = cross_8bit
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    assert main(["locate", str(colour), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert np.hypot(*(np.array(record["center_px"]) - truth.center)) < 0.02
