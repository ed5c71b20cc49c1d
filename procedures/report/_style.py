"""The report's stylesheet: one for the screen and, in the same file, the print rules (A4 pages with
running headers and page numbers) that the browser's print and the PDF use alike."""

from __future__ import annotations

SCREEN = """
body{font-family:"DejaVu Sans","Liberation Sans",Arial,sans-serif;margin:2em auto;max-width:1100px;color:#222;
 font-size:14px;line-height:1.35;padding:0 1em}
h1{font-size:1.5em;margin:0 0 .3em}h2{font-size:1.25em;margin:1.2em 0 .4em;border-bottom:1px solid #ccc}
h3{font-size:1.05em;margin:1em 0 .3em}
table{border-collapse:collapse;margin:.6em 0}th,td{border:1px solid #bbb;padding:2px 6px;text-align:right;
 vertical-align:top}
th{background:#eee;font-weight:600}td.l,th.l{text-align:left}caption{text-align:left;font-size:.9em;color:#444;
 padding:2px 0;caption-side:top}
table.kv th{width:13em}
.true,tr.true td{color:#2a7a2a}.bad{color:#b00}.muted{color:#777}.flag{background:#fdecea}
tr.worst td{border-top:2px solid #666;font-weight:600}
td small{color:#555;font-weight:normal}.u,.v{white-space:nowrap}td[nowrap]{white-space:nowrap}
table.nested{margin:0}table.nested th{width:auto;background:#f6f6f6}
code,.hash{font-family:"DejaVu Sans Mono",monospace;font-size:.92em;overflow-wrap:anywhere;word-break:break-all}
pre{background:#f6f6f6;padding:6px;font-size:11px;white-space:pre-wrap;overflow-wrap:anywhere;word-break:break-all}
pre.inline{margin:0;padding:0;background:none}
.note{font-size:.88em;color:#444}
.banner{border:2px solid #b00;background:#fff4f2;padding:.5em .9em;margin:.6em 0 1em}
.banner b{color:#b00}.banner ul{margin:.3em 0 0;padding-left:1.3em}
.banner.ok{border-color:#2a7a2a;background:#f2fbf2}.banner.ok b{color:#2a7a2a}
.banner.warn{border-color:#b86e00;background:#fff8ec}.banner.warn b{color:#8a5200}
tr.total td{border-top:2px solid #888}
.plots{display:flex;flex-wrap:wrap;gap:4px;break-inside:avoid}.plots svg{flex:0 0 auto}
table.signoff{width:100%}table.signoff td{height:3.6em}table.signoff th{white-space:nowrap}
table.signoff td.sign{width:32%}
.events td{font-size:.85em}table.events td:first-child{white-space:nowrap}
"""

PRINT = """
@media print{
 body{margin:0;max-width:none;padding:0;font-size:8.5pt}
 h1{font-size:15pt}h2{font-size:12pt}h3{font-size:10pt}
 section.part{break-before:page}
 h2,h3,caption{break-after:avoid}
 tr,.banner,.signoff,svg{break-inside:avoid}
 thead{display:table-header-group}
 table{width:100%}table.kv{width:auto;max-width:100%}
 th,td{padding:1px 4px}
 pre{font-size:6.5pt;padding:3px}
 .plots{display:block}.plots svg{width:57mm;height:auto;display:inline-block;margin:0 1mm 1mm 0}
 .plots.series svg{width:88mm}
 a{color:inherit;text-decoration:none}
}
"""


def css_string(text: str) -> str:
    """``text`` as a CSS string literal that cannot end the string or the ``<style>`` element."""
    out = []
    for ch in text:
        if ch in '"\\' or ch == "<" or ord(ch) < 0x20:
            out.append(f"\\{ord(ch):x} ")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def page_rules(*, run_id: str, procedure: str, robot: str, title: str) -> str:
    """The ``@page`` rules: A4, the run id, procedure and robot at the top of every page, page n of N below."""
    small = "font-size:7.5pt;color:#555;font-family:'DejaVu Sans',sans-serif"
    return (
        "@page{size:A4;margin:17mm 13mm 16mm 13mm;"
        f"@top-left{{content:{css_string('run ' + run_id)};{small}}}"
        f"@top-center{{content:{css_string(procedure)};{small}}}"
        f"@top-right{{content:{css_string(robot)};{small}}}"
        f"@bottom-left{{content:{css_string(title)};{small}}}"
        f"@bottom-right{{content:\"page \" counter(page) \" of \" counter(pages);{small}}}}}"
    )


def stylesheet(*, run_id: str, procedure: str, robot: str, title: str) -> str:
    """The whole ``<style>`` content of a report."""
    return SCREEN + PRINT + page_rules(run_id=run_id, procedure=procedure, robot=robot, title=title)
