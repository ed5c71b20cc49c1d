"""The report as a PDF, from the same HTML and its print stylesheet (WeasyPrint: CSS paged media,
running headers, page counters; it needs the OS's Pango, see docs/report.md)."""

from __future__ import annotations

import importlib
import logging

from procedures.station import RunError


class PdfUnavailable(RunError):
    """The PDF renderer (WeasyPrint and the Pango library under it) cannot be loaded here."""


def render_pdf(html: str) -> bytes:
    """The PDF of a report's HTML (A4, the print stylesheet's page headers and numbers).

    Parameters
    ----------
    html : a report from ``procedures.report._document.render_report`` (self-contained: no external resources).

    Returns
    -------
    bytes
        The PDF document.

    Raises
    ------
    PdfUnavailable
        WeasyPrint is not installed or cannot load Pango (one line saying what to install).
    """
    try:
        weasyprint = importlib.import_module("weasyprint")  # loaded only for a PDF: it loads Pango
    except ImportError:
        raise PdfUnavailable("PDF output needs the weasyprint package: pip install weasyprint") from None
    except OSError as exc:  # cffi could not open libpango / libgobject
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PdfUnavailable("PDF output needs the Pango library (Debian: apt-get install libpango-1.0-0 "
                             f"libpangoft2-1.0-0): {first}") from None
    # WeasyPrint logs every CSS property it skips (screen-only rules); the report's content is complete without them.
    logger = logging.getLogger("weasyprint")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        # The report is self-contained: nothing is fetched, whatever a stored text might name.
        fetcher = weasyprint.urls.URLFetcher(allowed_protocols=("data",), fail_on_errors=False)
        pdf = weasyprint.HTML(string=html, base_url=None, url_fetcher=fetcher).write_pdf()
    finally:
        logger.setLevel(level)
    if not isinstance(pdf, bytes):
        raise PdfUnavailable("weasyprint returned no PDF")
    return pdf
