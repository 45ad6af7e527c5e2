"""The lot report: one self-contained HTML page of what the results database says about a lot — its yield
per wafer with a map of each wafer's verdicts, the defect Pareto, the repeating defects, control charts of
the array-level readings and the stacked defect map — for a QC meeting or the lot's traveller.

Plots are inline SVG (the stacked map a PNG, one pixel block per lens), drawn here: no script library, no
network. A short script at the end counts the plots that drew (an SVG with marks of non-zero size, an
image that decoded) into the page's `data-rendered` (of `data-plots`), for people and for the headless
browser test.
"""

from __future__ import annotations

import base64
import html
import math
import re
from datetime import datetime, timezone

import numpy as np

from mlaqc import __version__
from mlaqc.report.maps import error_colour
from mlaqc.report.png import encode_png
from mlaqc.resultsdb import lot as views
from mlaqc.resultsdb.control import CUSUM_H, JUMP_Z, READINGS, RULES, Chart, lot_chart
from mlaqc.resultsdb.store import ResultsDB

# the control charts the report draws: the grid's, the assembly's (the mock production's drift is its distance)
CHART_READINGS = ("pitch_x_px", "rotation_deg", "distance_um", "mla_rotation_deg", "tilt_x_deg", "tilt_y_deg",
                  "flagged")
MAP_BLOCK_PX = 24  # each lens of the stacked map drawn at most this many pixels wide (at most 600 px in all)
_POSITION = re.compile(r"\((\d+)\s*,\s*(\d+)\)")  # a wafer position label "W(row,col)"

_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:0;color:#1f2328;background:#f6f8fa}
main{max-width:1200px;margin:0 auto;padding:0 16px 32px}
.banner{background:#24292f;color:#fff;padding:14px 20px;font-size:22px;font-weight:600}
.banner small{display:block;font-size:13px;font-weight:400;opacity:.85}
h2{margin:24px 0 8px;font-size:18px}
table{border-collapse:collapse;background:#fff}
th,td{border:1px solid #d0d7de;padding:3px 8px;text-align:left}td.num{text-align:right}
.plots{display:flex;flex-wrap:wrap;gap:12px}
figure.plot{background:#fff;border:1px solid #d0d7de;border-radius:6px;margin:0;padding:8px}
figcaption{font-size:13px;color:#57606a;margin-top:4px;max-width:560px}
.ooc{color:#cf222e}
"""

_SCRIPT = """
(function(){
  var figs = document.querySelectorAll("figure.plot"), drawn = 0;
  figs.forEach(function(f){
    var svg = f.querySelector("svg"), img = f.querySelector("img"), ok = false;
    if (svg) { var marks = svg.querySelectorAll("rect,circle,polyline,path,line");
               var box = svg.getBBox(); ok = marks.length > 0 && box.width > 0 && box.height > 0; }
    if (img) { ok = img.complete && img.naturalWidth > 0; }
    if (ok) { drawn += 1; f.dataset.rendered = "1"; }
  });
  document.body.dataset.plots = String(figs.length);
  document.body.dataset.rendered = String(drawn);
})();
"""


def _esc(v) -> str:
    return html.escape("" if v is None else str(v))


def _figure(body: str, caption: str) -> str:
    return f'<figure class="plot">{body}<figcaption>{_esc(caption)}</figcaption></figure>'


def _wafer_map(arrays: list[tuple[str, str]]) -> str:
    """SVG of one wafer's arrays coloured by verdict, at their "(row,col)" positions when the labels give
    them, else in inspection order on a square grid."""
    cells = []
    for k, (label, verdict) in enumerate(arrays):
        m = _POSITION.search(label or "")
        cells.append((int(m.group(1)), int(m.group(2))) if m else None)
    if any(c is None for c in cells):
        side = max(1, math.ceil(math.sqrt(len(arrays))))
        cells = [(k // side + 1, k % side + 1) for k in range(len(arrays))]
    rows, cols = max(r for r, _ in cells), max(c for _, c in cells)
    s = 22
    marks = "".join(
        f'<rect x="{(c - 1) * s + 1}" y="{(r - 1) * s + 1}" width="{s - 2}" height="{s - 2}" rx="3" '
        f'fill="{"#1a7f37" if v == "PASS" else "#cf222e"}"><title>{_esc(label)}: {_esc(v)}</title></rect>'
        for (r, c), (label, v) in zip(cells, arrays))
    return f'<svg width="{cols * s}" height="{rows * s}" role="img">{marks}</svg>'


def _pareto_svg(pareto: list[dict]) -> str:
    """Bars of the arrays each type failed, most costly first, with the cumulative share of lenses."""
    w, h, pad = 520, 220, 36
    top = max(d["arrays_failed"] for d in pareto)
    bw = (w - 2 * pad) / len(pareto)
    parts, cum, points = [], 0.0, []
    for k, d in enumerate(pareto):
        bh = (h - 2 * pad) * d["arrays_failed"] / top
        x = pad + k * bw
        r, g, b = error_colour(d["error_type"])
        parts.append(f'<rect x="{x + 4:.1f}" y="{h - pad - bh:.1f}" width="{bw - 8:.1f}" height="{max(bh, 1):.1f}" '
                     f'fill="rgb({r},{g},{b})" stroke="#57606a"><title>{_esc(d["error_type"])}: {d["arrays_failed"]} arrays, '
                     f'{d["lenses"]} lenses</title></rect>'
                     f'<text x="{x + bw / 2:.1f}" y="{h - pad + 14}" font-size="11" text-anchor="middle">'
                     f'{_esc(d["error_type"])}</text>')
        cum += d["share"]
        points.append(f"{x + bw / 2:.1f},{h - pad - (h - 2 * pad) * cum:.1f}")
    parts.append(f'<polyline points="{" ".join(points)}" fill="none" stroke="#24292f" stroke-width="1.5"/>')
    parts.append(f'<text x="{pad}" y="{pad - 10}" font-size="11">arrays failed (bars, max {top}); cumulative share '
                 'of lenses out of tolerance (line)</text>')
    return f'<svg width="{w}" height="{h}" role="img">{"".join(parts)}</svg>'


def _chart_svg(chart: Chart, reading: str) -> str:
    """A control chart: the values with the centre line they were judged against and its limits (I-MR: 3
    sigma; CUSUM: each array's jump limits, `Chart.jump_limits`), the baseline shaded, the points out of
    control in red; a CUSUM chart adds its two sums under them, with the decision interval h."""
    w, pad = 560, 30
    cusum = chart.kind == "cusum" and chart.cusum is not None
    h_top = 220
    height = h_top + (130 if cusum else 0)
    v = chart.values
    if not cusum:
        centre = np.full(v.size, chart.centre)
        low, high = centre - 3 * chart.sigma, centre + 3 * chart.sigma
    else:  # each array's jump limits, from the arrays before it (wide while they are few)
        centre = np.where(np.isfinite(chart.centre_at), chart.centre_at, chart.centre)
        low, high = chart.jump_limits()
        # the axis holds the values and the limits, these no farther out than the values' own span again
        span_v = float(v.max() - v.min()) or max(chart.sigma, abs(float(v.max())), 1.0)
        low = np.clip(np.where(np.isfinite(low), low, centre), v.min() - span_v, None)
        high = np.clip(np.where(np.isfinite(high), high, centre), None, v.max() + span_v)
    lo = min(float(v.min()), float(np.min(low)))
    hi = max(float(v.max()), float(np.max(high)))
    span = hi - lo or max(abs(hi), 1.0)  # a reading without spread: drawn on a line at mid height
    lo -= 0.5 * span if hi == lo else 0.0
    n = max(v.size - 1, 1)

    def x(i):
        return pad + (w - 2 * pad) * i / n

    def y(val):
        return h_top - pad - (h_top - 2 * pad) * (val - lo) / span

    def line(values, colour, dash=""):  # from the first array judged on (a CUSUM's limits move with it)
        first = min(chart.baseline, v.size - 1) if cusum else 0
        return _polyline([(x(i), y(values[i])) for i in range(first, v.size)], colour, f'stroke-dasharray="{dash}"')

    parts = [f'<rect x="{pad}" y="{pad}" width="{x(chart.baseline - 1) - pad:.1f}" height="{h_top - 2 * pad}" '
             'fill="#eaeef2"><title>baseline: the process known good, not judged</title></rect>',
             line(centre, "#24292f"), line(high, "#cf222e", "4 3"), line(low, "#cf222e", "4 3")]
    parts.append(_polyline([(x(i), y(val)) for i, val in enumerate(v)], "#0969da", 'stroke-width="1.2"'))
    for i, val in enumerate(v):
        bad = i in chart.signals
        parts.append(f'<circle cx="{x(i):.1f}" cy="{y(val):.1f}" r="{3 if bad else 2}" '
                     f'fill="{"#cf222e" if bad else "#0969da"}"><title>{_esc(chart.labels[i])}: {val:.6g}</title></circle>')
    spread = f"sigma {chart.sigma:.3g}" if chart.sigma > 0 else "no spread in the baseline"
    parts.append(f'<text x="{pad}" y="{pad - 10}" font-size="11">{_esc(READINGS[reading])}: centre '
                 f'{chart.centre:.6g}, {spread}</text>')
    if cusum:
        parts.append(_cusum_panel(chart, x, h_top, pad))
    return f'<svg width="{w}" height="{height}" role="img">{"".join(parts)}</svg>'


def _cusum_panel(chart: Chart, x, top: float, pad: float) -> str:
    """The upper (red) and lower (blue) CUSUMs under a chart, in sigmas, with the decision interval h."""
    height = 100
    peak = max(float(chart.cusum.max()), chart.h, 1e-9) * 1.1

    def y(val):
        return top + height - (height - 10) * val / peak

    def line(values, colour):
        return _polyline([(x(i), y(val)) for i, val in enumerate(values)], colour, 'stroke-width="1.2"')

    return (f'<line x1="{pad}" x2="{x(chart.values.size - 1):.1f}" y1="{y(chart.h):.1f}" y2="{y(chart.h):.1f}" '
            f'stroke="#cf222e" stroke-dasharray="4 3"><title>h = {chart.h:g} sigma</title></line>'
            f'<line x1="{pad}" x2="{x(chart.values.size - 1):.1f}" y1="{y(0):.1f}" y2="{y(0):.1f}" stroke="#8c959f"/>'
            + line(chart.cusum[0], "#cf222e") + line(chart.cusum[1], "#0969da")
            + f'<text x="{pad}" y="{top + 6:.0f}" font-size="11">CUSUM, sigmas: rise (red), fall (blue), h {chart.h:g} '
            "(dashed)</text>")


def _polyline(points: list[tuple[float, float]], colour: str, style: str = "") -> str:
    """An SVG polyline through `points` (x, y in px), unfilled, in `colour`, with extra attributes `style`."""
    return (f'<polyline points="{" ".join(f"{px:.1f},{py:.1f}" for px, py in points)}" fill="none" '
            f'stroke="{colour}" {style}/>')


def _stacked_map_img(counts: dict, arrays: int, shape: tuple[int, int]) -> str:
    """The stacked defect map as a PNG (white: never flagged, to dark red: flagged in every array)."""
    rows, cols = shape
    share = np.zeros((rows, cols))
    for (m, n), k in counts.items():
        if 1 <= m <= rows and 1 <= n <= cols:
            share[m - 1, n - 1] = k / max(arrays, 1)
    block = max(1, min(MAP_BLOCK_PX, 600 // max(rows, cols, 1)))
    t = np.repeat(np.repeat(share, block, axis=0), block, axis=1)
    rgb = np.stack([255 - 80 * t, 255 * (1 - t), 255 * (1 - t)], axis=-1).clip(0, 255).astype(np.uint8)
    data = base64.b64encode(encode_png(rgb, level=6)).decode()
    return (f'<img alt="stacked defect map" width="{rgb.shape[1]}" height="{rgb.shape[0]}" '
            f'src="data:image/png;base64,{data}">')


def lot_report_html(db: ResultsDB, lot: str | None = None, wafer: str | None = None,
                    readings=CHART_READINGS, baseline: int = 20, kind: str = "cusum", rules=tuple(RULES),
                    h: float = CUSUM_H) -> str:
    """The lot report page (see the module docstring) of the selection."""
    yields = views.yield_table(db, lot, wafer)
    if not yields:
        from mlaqc.errors import InputError

        raise InputError(f"nothing is recorded for lot {lot!r}" if lot else "nothing is recorded in the database")
    pareto = views.pareto(db, lot, wafer)
    repeats = views.repeating_defects(db, lot, wafer)
    counts, arrays, shape = views.stacked_map(db, lot, wafer)
    by_wafer: dict[str, list] = {}
    for w, label, verdict, *_ in views.arrays(db, lot, wafer):
        by_wafer.setdefault(w or "-", []).append((label, verdict))
    total = sum(y["arrays"] for y in yields)
    passed = sum(y["passed"] for y in yields)
    title = f"Lot {lot}" if lot else "All lots"
    out = [f'<!doctype html><html><head><meta charset="utf-8"><title>{_esc(title)}: mlaqc lot report</title>',
           f"<style>{_CSS}</style></head><body>",
           f'<div class="banner">{_esc(title)}: yield {passed}/{total} ({passed / total:.1%})'
           f'<small>mlaqc {__version__}, {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC; each array by its latest '
           "inspection</small></div><main>",
           "<h2>Yield per wafer</h2><table><tr><th>lot</th><th>wafer</th><th>arrays</th><th>passed</th>"
           "<th>failed</th><th>yield</th></tr>",
           *(f'<tr><td>{_esc(y["lot"])}</td><td>{_esc(y["wafer"])}</td><td class="num">{y["arrays"]}</td>'
             f'<td class="num">{y["passed"]}</td><td class="num">{y["failed"]}</td>'
             f'<td class="num">{y["yield"]:.1%}</td></tr>' for y in yields),
           '</table><h2>Wafer maps</h2><div class="plots">',
           *(_figure(_wafer_map(a), f"wafer {w}: {sum(v == 'PASS' for _, v in a)} of {len(a)} arrays pass "
                     "(green PASS, red FAIL)") for w, a in by_wafer.items()),
           "</div>"]
    if pareto:
        out += ['<h2>Defect Pareto</h2><div class="plots">',
                _figure(_pareto_svg(pareto), "the defect types that failed arrays, most costly first"), "</div>"]
    out.append("<h2>Repeating defects</h2>")
    out.append("<ul>" + "".join(f"<li>{_esc(d.sentence())}</li>" for d in repeats) + "</ul>" if repeats else
               "<p>No lens is flagged in more arrays than chance explains.</p>")
    out.append("<h2>Control charts</h2><p>" + (
        f"Self-starting CUSUM: each array judged against the mean and spread of every array before it (the first "
        f"{baseline} not judged), out of control while a sum of its scores passes h = {h:g} sigma, or beyond "
        f"{JUMP_Z:g} sigma on its own." if kind == "cusum" else
        f"Individuals chart, limits from the first {baseline} arrays, run rules {', '.join(map(str, rules))}.")
        + '</p><div class="plots">')
    for reading in readings:
        chart = lot_chart(db, reading, lot, wafer, baseline, rules, kind, h)
        left = "; ".join(([f"not charted (reading not finite): {'; '.join(chart.not_charted)}"] if chart.not_charted
                          else []) + ([chart.unread_words()] if chart.not_read else []))
        if chart.values.size < 3:
            if left:
                out.append(f"<p>{_esc(READINGS[reading])}: fewer than 3 arrays to chart; {_esc(left)}</p>")
            continue
        named = "; ".join(chart.labels[i] for i in sorted(chart.signals)) or "none"
        out.append(_figure(_chart_svg(chart, reading),
                           f"{READINGS[reading]}: out of control: {named}" + (f"; {left}" if left else "")))
    out.append("</div>")
    if arrays and shape[0] and shape[1]:
        out += ['<h2>Stacked defect map</h2><div class="plots">',
                _figure(_stacked_map_img(counts, arrays, shape),
                        f"how often each lens is flagged across the {arrays} arrays ({shape[0]} x {shape[1]} "
                        "lenses; white never, dark red in every one)"), "</div>"]
    out.append(f"</main><script>{_SCRIPT}</script></body></html>")
    return "\n".join(out)
