"""``instrument report RUN --pdf``: the PDF is read back (pdfminer.six) and checked for the banner,
the table values, the running headers and page numbers, the sign-off block, and no text off the page."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from instrument import ARCSEC
from procedures.cli import main
from procedures.report import PdfUnavailable, render_pdf, render_report, robot_label
from tests.test_report import as_stored_by_older_code, fake_run, with_stored_figures

pdfminer = pytest.importorskip("pdfminer.high_level", reason="pdfminer.six (a test dependency) reads the PDF back")
from pdfminer.layout import LTTextLine  # noqa: E402  (after the skip: only with pdfminer installed)


@pytest.fixture(scope="module", autouse=True)
def pdf_renderer():
    try:
        render_pdf("<p>probe</p>")
    except PdfUnavailable as exc:  # .ci/run installs Pango; a machine without it cannot make PDFs
        pytest.skip(str(exc))


def pages(path: Path) -> list[tuple[float, float, list[tuple[float, float, str]]]]:
    """Per page: its width, height and text lines as (x0, x1, text)."""
    def text_lines(item) -> list[tuple[float, float, str]]:
        if isinstance(item, LTTextLine):
            return [(item.x0, item.x1, item.get_text().strip())]
        return [line for child in getattr(item, "_objs", None) or [] for line in text_lines(child)]

    return [(page.width, page.height, text_lines(page)) for page in pdfminer.extract_pages(str(path))]


@pytest.fixture(scope="module")
def iso_pdf(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pdf")
    run, _, _ = fake_run(tmp, "iso9283_repeatability", name="'ISO 9283, 30 cycles'", cycles=5)
    path = tmp / "report.pdf"
    assert main(["report", run["id"][:8], "--pdf", "-o", str(path), "--runs-dir", str(tmp / "runs")]) == 0
    return run, pages(path), tmp


def test_pdf_has_the_banner_and_the_table_values_on_its_first_page(iso_pdf):
    run, doc, _ = iso_pdf
    first = " ".join(text for _, _, text in doc[0][2])
    assert "ISO 9283 pose repeatability and accuracy — 5 cycles" in first
    assert "Deviations from ISO 9283" in first and re.search(r"5 cycles measured.*\(ISO 9283 asks for 30\)", first)
    text = " ".join(t for _, _, lines in doc for _, _, t in lines)
    for label in run["results"]["order"]:
        stats = run["results"]["points"][label]["stats"]
        assert f"{stats['rp_l'] * 1e6:.2f}" in text and f"{stats['rp_a'] / ARCSEC:.2f}" in text
        assert f"{math.degrees(stats['rp_a']):.6f}°" in text


def test_every_page_has_the_running_header_and_its_number(iso_pdf):
    run, doc, _ = iso_pdf
    assert len(doc) >= 4
    for number, (_, _, lines) in enumerate(doc, start=1):
        text = [t for _, _, t in lines]
        assert f"page {number} of {len(doc)}" in text
        assert f"run {run['id']}" in text and "ISO 9283, 30 cycles" in text and robot_label(run) in text


def test_the_sign_off_block_is_on_one_page(iso_pdf):
    _, doc, _ = iso_pdf
    holding = [n for n, (_, _, lines) in enumerate(doc) if any(t == "Sign-off" for _, _, t in lines)]
    assert len(holding) == 1
    text = [t for _, _, t in doc[holding[0]][2]]
    for line in ("Prepared by", "Checked by", "Approved by", "name", "function", "date", "signature"):
        assert line in text


def test_no_text_runs_off_the_page(iso_pdf):
    _, doc, _ = iso_pdf
    for width, _, lines in doc:
        for x0, x1, text in lines:
            assert 0 <= x0 and x1 <= width, f"off the page: {text!r} at {x0:.0f}–{x1:.0f} of {width:.0f}"


def test_default_pdf_path_is_in_the_runs_folder(iso_pdf, capsys):
    run, _, tmp = iso_pdf
    assert main(["report", run["id"], "--pdf", "--runs-dir", str(tmp / "runs")]) == 0
    path = Path(capsys.readouterr().out.strip())
    assert path == tmp / "runs" / run["id"] / "report.pdf" and path.read_bytes().startswith(b"%PDF-")


def test_pdf_of_stored_figures_shows_value_u_and_conditions(iso_pdf, tmp_path):
    run, _, tmp = iso_pdf
    from procedures.store import RunStore

    with RunStore(tmp / "runs") as store:
        stored = with_stored_figures(as_stored_by_older_code(store.get_run(run["id"])))
        html = render_report(stored, store.samples(run["id"]), store.events(run["id"]))
    path = tmp_path / "figures.pdf"
    path.write_bytes(render_pdf(html))
    doc = pages(path)
    text = " ".join(t for _, _, lines in doc for _, _, t in lines)
    fig = stored["results"]["figures"]["points"]["P1"]["rp_l"]
    assert f"{fig['value'] * 1e6:.2f} ± {fig['expanded_uncertainty'] * 1e6:.2f}" in text
    assert "20235500123" in text and "250.0 mm/s" in text and "20.50 °C" in text
    assert all("Universal Robots UR5e s/n 20235500123" in [t for _, _, t in lines] for _, _, lines in doc)
    assert re.search(r"5 cycles measured at P1", text)


def test_an_unwritable_pdf_path_is_one_line(iso_pdf, tmp_path, capsys):
    run, _, tmp = iso_pdf
    code = main(["report", run["id"], "--pdf", "-o", str(tmp_path / "missing" / "r.pdf"), "--runs-dir",
                 str(tmp / "runs")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "cannot write" in err and "Traceback" not in err
