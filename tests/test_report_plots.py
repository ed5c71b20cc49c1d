"""The report's plots, read back from their SVG: equal scales, the RP circle, the legend off the data,
the per-cycle series."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from procedures.report import Circle, figure, lines, render_report, scatter
from tests.test_report import fake_run

SVG = "{http://www.w3.org/2000/svg}"


def svgs(html: str) -> list[ET.Element]:
    return [ET.fromstring(m) for m in re.findall(r"<svg .*?</svg>", html, flags=re.S)]


def scale(svg: ET.Element, axis: str) -> tuple[float, float]:
    """(pixels per data unit, pixel of data value 0) read off the drawn ticks of ``axis`` ("x" or "y")."""
    ticks = [(float(g.get("data-value")), float(g.get("data-px"))) for g in svg.iter(f"{SVG}g")
             if g.get("class") == f"{axis}tick"]
    assert len(ticks) >= 2, f"fewer than 2 {axis} ticks"
    (v0, p0), (v1, p1) = ticks[0], ticks[-1]
    per_unit = abs(p1 - p0) / (v1 - v0)
    return per_unit, p0 + (p1 - p0) * (0 - v0) / (v1 - v0)


def plot_area(svg: ET.Element) -> tuple[float, float, float, float]:
    rect = next(svg.iter(f"{SVG}rect"))
    x, y, w, h = (float(rect.get(k)) for k in ("x", "y", "width", "height"))
    return x, y, x + w, y + h


def data_points(svg: ET.Element) -> list[tuple[float, float]]:
    return [(float(c.get("cx")), float(c.get("cy"))) for g in svg.iter(f"{SVG}g") if g.get("class") == "series"
            for c in g.iter(f"{SVG}circle")]


def test_equal_aspect_gives_one_scale_for_both_axes():
    rng = np.random.default_rng(0)
    xs, ys = rng.normal(0, 50, 30), rng.normal(0, 5, 30)  # x spread 10× y's
    equal = ET.fromstring(scatter([("p", xs, ys)], title="t", xlabel="x", ylabel="y", equal_aspect=True))
    assert scale(equal, "x")[0] == pytest.approx(scale(equal, "y")[0], rel=1e-3)
    free = ET.fromstring(scatter([("p", xs, ys)], title="t", xlabel="x", ylabel="y"))
    assert scale(free, "y")[0] > 3 * scale(free, "x")[0]  # without it, y would be stretched


def test_the_circle_has_its_radius_in_data_units_and_every_point_is_inside_the_frame():
    rng = np.random.default_rng(1)
    xs, ys = rng.normal(0, 3, 20), rng.normal(0, 1, 20)
    svg = ET.fromstring(scatter([("p", xs, ys)], title="t", xlabel="x", ylabel="y", equal_aspect=True,
                                circles=[Circle(0.0, 0.0, 12.5, "RP_l = 12.50 µm")]))
    per_unit, x0 = scale(svg, "x")
    _, y0 = scale(svg, "y")
    circle = next(c for c in svg.iter(f"{SVG}circle") if c.get("class") == "circle")
    assert float(circle.get("r")) / per_unit == pytest.approx(12.5, rel=1e-3)
    assert (float(circle.get("cx")), float(circle.get("cy"))) == pytest.approx((x0, y0), abs=0.01)
    left, top, right, bottom = plot_area(svg)
    cx, cy, r = (float(circle.get(k)) for k in ("cx", "cy", "r"))
    assert left <= cx - r and cx + r <= right and top <= cy - r and cy + r <= bottom  # the circle is kept in range


def test_the_legend_sits_below_the_plot_area():
    svg = ET.fromstring(scatter([("measured", [0, 1], [0, 1]), ("true (simulation)", [0, 1], [1, 0])], title="t",
                                xlabel="x", ylabel="y", circles=[Circle(0, 0, 1, "RP_l = 1 µm")]))
    _, _, _, bottom = plot_area(svg)
    legend = [t for t in svg.iter(f"{SVG}text") if "measured" in "".join(t.itertext())
              or "true (simulation)" in "".join(t.itertext()) or "RP" in "".join(t.itertext())]
    assert len(legend) == 3 and all(float(t.get("y")) > bottom + 20 for t in legend)  # below the axis label too
    assert all(y <= bottom for _, y in data_points(svg))


@pytest.fixture(scope="module")
def iso_report(tmp_path_factory):
    run, samples, events = fake_run(tmp_path_factory.mktemp("plots"), "iso9283_repeatability", cycles=6)
    return run, render_report(run, samples, events)


def test_report_position_plots_are_equal_aspect_with_the_rp_circle(iso_report):
    run, html = iso_report
    plots = [s for s in svgs(html) if any(c.get("class") == "circle" for c in s.iter(f"{SVG}circle"))]
    assert len(plots) == 15  # x–y, x–z, y–z for each of the 5 points
    for index, svg in enumerate(plots):
        label = run["results"]["order"][index // 3]
        per_x, x0 = scale(svg, "x")
        per_y, y0 = scale(svg, "y")
        assert per_x == pytest.approx(per_y, rel=2e-3)
        rp_l_um = figure(run["results"], label, "rp_l").value * 1e6  # the RP_l the table reports
        circle = next(c for c in svg.iter(f"{SVG}circle") if c.get("class") == "circle")
        assert float(circle.get("r")) / per_x == pytest.approx(rp_l_um, rel=2e-3)
        assert (float(circle.get("cx")), float(circle.get("cy"))) == pytest.approx((x0, y0), abs=0.05)  # barycentre
        assert len(data_points(svg)) == 12  # 6 measured + 6 true poses
        # the measured points, read back in µm about the barycentre, are the stored poses
        poses = np.asarray(run["results"]["points"][label]["poses"])[:, :3] * 1e6
        i, j = [(0, 1), (0, 2), (1, 2)][index % 3]
        measured = data_points(svg)[:6]
        back_x = [(px - x0) / per_x for px, _ in measured]
        back_y = [(y0 - py) / per_y for _, py in measured]
        assert back_x == pytest.approx(list(poses[:, i] - poses[:, i].mean()), abs=0.1 / per_x + 1e-6)
        assert back_y == pytest.approx(list(poses[:, j] - poses[:, j].mean()), abs=0.1 / per_y + 1e-6)


def test_report_has_per_cycle_series_for_every_point(iso_report):
    run, html = iso_report
    series = [s for s in svgs(html) if "mean pose" in "".join(next(s.iter(f"{SVG}text")).itertext())]
    assert len(series) == 10  # position and orientation for each of the 5 points
    for svg in series:
        polylines = list(svg.iter(f"{SVG}polyline"))
        assert len(polylines) == 3 and all(len(p.get("points").split()) == 6 for p in polylines)
        per_x, x0 = scale(svg, "x")
        first_x = float(polylines[0].get("points").split()[0].split(",")[0])
        assert (first_x - x0) / per_x == pytest.approx(1.0, abs=0.01)  # cycles are numbered from 1


def test_lines_break_at_missing_values():
    svg = ET.fromstring(lines([("a", [1, 2, 3, 4, 5], [0.0, 1.0, float("nan"), 2.0, 3.0])], title="t", xlabel="x",
                              ylabel="y"))
    assert [len(p.get("points").split()) for p in svg.iter(f"{SVG}polyline")] == [2, 2]
