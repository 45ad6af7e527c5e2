"""report.html: one self-contained page (verdict, summary, defect map, sortable defect table, gallery)."""

from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc import __version__
from mlaqc.inspection.results import METRICS, Defect, detection_limit_text
from mlaqc.report.document import REPORT_FILES
from mlaqc.report.maps import _encode_png, error_colour
from mlaqc.report.view import View

GALLERY_MAX = 200

_CSS = """
body{font:14px/1.4 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;color:#1f2328;background:#f6f8fa}
main{max-width:1200px;margin:0 auto;padding:0 16px 32px}
.banner{color:#fff;padding:14px 20px;font-size:22px;font-weight:600}
.banner.PASS{background:#1a7f37}.banner.FAIL{background:#cf222e}
.banner small{font-weight:400;font-size:14px;opacity:.9;display:block;word-break:break-all}
h2{margin:24px 0 8px;font-size:18px}
.cards{display:flex;flex-wrap:wrap;gap:8px}
.card{background:#fff;border:1px solid #d0d7de;border-radius:6px;padding:8px 12px;min-width:90px}
.card b{display:block;font-size:20px}
.sw{display:inline-block;width:12px;height:12px;border-radius:2px;margin-right:4px;vertical-align:-1px;
border:1px solid #0003}
table{border-collapse:collapse;background:#fff}
th,td{border:1px solid #d0d7de;padding:3px 8px;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
table.sortable th{cursor:pointer;user-select:none;background:#eaeef2;position:sticky;top:0}
table.sortable th::after{content:" \\2195";color:#8c959f}
table.sortable th[aria-sort=ascending]::after{content:" \\25B2";color:#1f2328}
table.sortable th[aria-sort=descending]::after{content:" \\25BC";color:#1f2328}
tr.out td:last-child{color:#cf222e;font-weight:600}
.map img{max-width:100%;height:auto;border:1px solid #d0d7de}
.gallery{display:flex;flex-wrap:wrap;gap:12px}
.lens{background:#fff;border:1px solid #d0d7de;border-radius:6px;padding:8px;width:300px}
.lens h3{margin:0 0 6px;font-size:15px}
.pair{display:flex;gap:8px}
.pair figure{margin:0;text-align:center;font-size:12px;color:#57606a}
.pair img{image-rendering:pixelated;display:block;border:1px solid #d0d7de}
.lens table{font-size:12px;margin-top:6px;width:100%}
.lens td{padding:1px 4px}
.lens th{font-weight:600;background:#eaeef2;padding:1px 4px}
.note{color:#57606a}
pre{background:#fff;border:1px solid #d0d7de;padding:8px;overflow:auto;max-height:400px}
"""

_JS = """
(function () {
  function key(row, i) {
    var c = row.cells[i];
    return c.hasAttribute('data-sort') ? c.getAttribute('data-sort') : c.textContent.trim();
  }
  function sortBy(table, th, i) {
    var asc = th.getAttribute('aria-sort') !== 'ascending';
    var num = th.getAttribute('data-type') === 'num';
    var heads = table.tHead.rows[0].cells;
    for (var h = 0; h < heads.length; h++) heads[h].removeAttribute('aria-sort');
    th.setAttribute('aria-sort', asc ? 'ascending' : 'descending');
    var body = table.tBodies[0];
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function (a, b) {
      var x = key(a, i), y = key(b, i), r;
      if (num) {
        x = x === '' ? NaN : parseFloat(x); y = y === '' ? NaN : parseFloat(y);
        if (isNaN(x) || isNaN(y)) return isNaN(x) - isNaN(y);  /* blanks last either way */
        r = x - y;
      } else {
        r = x.localeCompare(y);
      }
      return asc ? r : -r;
    });
    for (var k = 0; k < rows.length; k++) body.appendChild(rows[k]);
  }
  var tables = document.querySelectorAll('table.sortable');
  for (var t = 0; t < tables.length; t++) {
    (function (table) {
      var heads = table.tHead.rows[0].cells;
      for (var i = 0; i < heads.length; i++) {
        (function (th, i) {
          th.addEventListener('click', function () { sortBy(table, th, i); });
          th.addEventListener('keydown', function (e) {
            if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); sortBy(table, th, i); }
          });
        })(heads[i], i);
      }
    })(tables[t]);
  }
})();
"""

_E = html.escape


def _num(x: float | None, digits: int = 4) -> str:
    """A number for people: `digits` significant digits, '∞' for infinity, '' for None/NaN."""
    if x is None or math.isnan(x):
        return ""
    if math.isinf(x):
        return "∞" if x > 0 else "-∞"
    return f"{x:.{digits}g}"


def _sort_key(x: float | None) -> str:
    """A number for the table's data-sort (JavaScript parseFloat); '' sorts last."""
    if x is None or math.isnan(x):
        return ""
    if math.isinf(x):
        return "Infinity" if x > 0 else "-Infinity"
    return repr(float(x))


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _severity(d: Defect) -> tuple:
    score = d.score if math.isfinite(d.score) else -math.inf
    return (d.within_tolerance, -score, d.m, d.n)


def _html(v: View, report: dict[str, Any], small_png: bytes, lens_png: bytes | None = None) -> str:
    r = v.result
    s, g = report["summary"], report["grid_summary"]
    defects = sorted(r.defects, key=_severity)
    out: list[str] = []
    w = out.append
    w("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n")
    w("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n")
    w(f"<title>{_E(r.verdict)} — MLA inspection of {_E(Path(str(r.source)).name)}</title>\n")
    w(f"<style>{_CSS}</style>\n</head>\n<body>\n")
    w(f"<div class=\"banner {_E(r.verdict)}\" id=\"verdict\">{_E(r.verdict)}"
      f"<small>source: {_E(str(r.source))} · {_E(report['created_utc'])} · mlaqc {_E(__version__)}</small></div>\n")
    w("<main>\n<h2>Summary</h2>\n<div class=\"cards\">\n")
    cards = [("lenses", f"{s['lens_count']}", f"{s['rows']} × {s['cols']}"), ("found", f"{s['found']}", ""),
             ("missing", f"{s['missing']}", ""), ("flagged", f"{s['flagged']}", ""),
             ("out of tolerance", f"{s['out_of_tolerance']}", ""),
             ("pitch", f"{_num(g['pitch_px'], 5)} px", ""), ("rotation", f"{_num(g['rotation_deg'], 3)}°", ""),
             ("RMS residual", f"{_num(g['rms_residual_px'], 3)} px", "")]
    for label, value, extra in cards:
        w(f"<div class=\"card\"><b>{_E(value)}</b>{_E(label)}"
          + (f" <span class=\"note\">{_E(extra)}</span>" if extra else "") + "</div>\n")
    w("</div>\n")
    if s["by_error_type"]:
        w("<p>")
        w(" &nbsp; ".join(f"{_swatch(t)}{_E(t)}: {n}" for t, n in s["by_error_type"].items()))
        w("</p>\n")
    w(f"<p id=\"detection-limit\"><b>This frame {_E(detection_limit_text(report.get('detection_limit') or {}))}"
      f"</b> <span class=\"note\">(at {_E(_num(r.tolerances.get('detect_sigma'), 3))} σ; a PASS says nothing about "
      f"smaller errors. {s.get('not_inspected', 0)} lenses off the sensor not inspected, {s.get('below_reportable', 0)} "
      f"significant deviations below the minimum reportable size.)</span></p>\n")
    for note in r.notes:
        w(f"<p class=\"note\">{_E(str(note))}</p>\n")
    lattice = report["conventions"].get("lattice") or {}
    w(f"<p id=\"lattice\"><b>Lattice: {_E(str(lattice.get('packing', 'square')))}</b>{_E(_aperture_text(report))} "
      f"<span class=\"note\">{_E(str(report['conventions'].get('lens', '')))}</span></p>\n")

    w("<h2>Defect map</h2>\n<div class=\"map\">")
    w(f"<a href=\"{_E(REPORT_FILES['defect_map'])}\"><img id=\"defect-map\" alt=\"defect map\" "
      f"src=\"{_data_uri(small_png)}\"></a></div>\n")
    ring = "Hexagon (the lens' cell) colour" if v.hex else "Ring colour"
    w(f"<p class=\"note\">{ring} = error type, thick ring = out of tolerance, cross = missing lens, "
      f"tick = direction. Full resolution: <a href=\"{_E(REPORT_FILES['defect_map'])}\">"
      f"{_E(REPORT_FILES['defect_map'])}</a>; every lens: <a href=\"{_E(REPORT_FILES['csv'])}\">"
      f"{_E(REPORT_FILES['csv'])}</a>.</p>\n")

    _assembly_section(w, report.get("assembly"))
    _measurement_section(w, report.get("measurements"), lens_png, v.hex)
    _through_focus_section(w, report.get("through_focus"))

    w(f"<h2>Flagged lenses ({len(defects)})</h2>\n")
    if defects:
        w("<p class=\"note\">Click a column heading to sort. U(m,n): row m from the top, column n from the "
          "left. Direction: degrees counterclockwise from the image's +x axis.</p>\n")
        w("<table class=\"sortable\" id=\"defects\">\n<thead><tr>")
        for name, kind in (("U(m,n)", "num"), ("type", "str"), ("magnitude", "num"), ("direction °", "num"),
                           ("score", "num"), ("tolerance", "str")):
            w(f"<th tabindex=\"0\" data-type=\"{kind}\" scope=\"col\">{_E(name)}</th>")
        w("</tr></thead>\n<tbody>\n")
        for d in defects:
            row_cls = ' class="out"' if not d.within_tolerance else ""
            w(f"<tr{row_cls}>"
              f"<td data-sort=\"{d.m * 100000 + d.n}\"><a href=\"#U{d.m}-{d.n}\">U({d.m},{d.n})</a></td>"
              f"<td>{_swatch(d.error_type)}{_E(d.error_type)}</td>"
              f"<td class=\"num\" data-sort=\"{_sort_key(d.magnitude)}\">{_E(_num(d.magnitude))} {_E(d.unit)}</td>"
              f"<td class=\"num\" data-sort=\"{_sort_key(d.direction_deg)}\">{_E(_num(d.direction_deg, 3))}</td>"
              f"<td class=\"num\" data-sort=\"{_sort_key(d.score)}\">{_E(_num(d.score, 3))}</td>"
              f"<td>{'within' if d.within_tolerance else 'OUT'}</td></tr>\n")
        w("</tbody>\n</table>\n")
    else:
        w("<p>No lens was flagged.</p>\n")

    if defects:
        shown = defects[:GALLERY_MAX]
        w("<h2>Sub-images of flagged lenses</h2>\n")
        if len(defects) > len(shown):
            w(f"<p class=\"note\" id=\"gallery-cap\">Showing the {len(shown)} most severe of {len(defects)} "
              f"flagged lenses; every lens is in {_E(REPORT_FILES['csv'])}.</p>\n")
        w("<p class=\"note\">Each lens' sub-image beside its reference, enlarged without smoothing, both on "
          "the same grey scale; its indexes beside the median over all lenses.</p>\n<div class=\"gallery\">\n")
        medians = _metric_medians(v)
        for d in shown:
            w(_lens_card(v, d, medians))
        w("</div>\n")

    w("<h2>Grid, tolerances, timings</h2>\n<table>\n")
    rows = [(f"grid {k}", _num(val, 6) if isinstance(val, float) else str(val)) for k, val in g.items()]
    rows += [(f"tolerance {k}", _num(val, 6) if isinstance(val, float) else str(val))
             for k, val in report["tolerances"].items()]
    rows += [(f"time {k}", f"{_num(val, 3)} s" if isinstance(val, (int, float)) else str(val))
             for k, val in report["timings_s"].items()]
    for k, val in rows:
        w(f"<tr><td>{_E(k)}</td><td class=\"num\">{_E(val)}</td></tr>\n")
    w("</table>\n")
    if report.get("config") is not None:
        w("<details><summary>Configuration</summary><pre>")
        w(_E(json.dumps(report["config"], indent=2, ensure_ascii=False)))
        w("</pre></details>\n")
    w(f"</main>\n<script>{_JS}</script>\n</body>\n</html>\n")
    return "".join(out)


ASSEMBLY_ROWS = (("mla_sensor_distance_um", "MLA–sensor distance (change from design)", "µm", 2),
                 ("distance_from_focus_um", "the same, from the sub-images' focus", "µm", 2),
                 ("mla_rotation_deg", "rotation about the optical axis", "°", 4),
                 ("mla_tilt_x_deg", "tilt about x", "°", 3), ("mla_tilt_y_deg", "tilt about y", "°", 3),
                 ("mla_shift_x_um", "shift x", "µm", 2), ("mla_shift_y_um", "shift y", "µm", 2))


def _assembly_section(w, a: dict[str, Any] | None) -> None:
    """The array's placement in the camera: each reading ± 1σ, the bounds it exceeds, what it assumes."""
    if not a:
        return
    w("<h2>Assembly</h2>\n")
    if a.get("not_read"):
        w(f"<p id=\"assembly\">Not read: {_E(a['not_read'])}.</p>\n")
        return
    w("<table id=\"assembly\">\n<thead><tr><th scope=\"col\">reading</th><th scope=\"col\">value</th>"
      "<th scope=\"col\">1σ</th></tr></thead>\n<tbody>\n")
    for key, label, unit, digits in ASSEMBLY_ROWS:
        item = a.get(key) or {}
        value, sigma = item.get("value"), item.get("sigma")
        w(f"<tr><td>{_E(label)} <span class=\"note\">{_E(key)}</span></td>"
          f"<td class=\"num\">{'–' if value is None else _E(f'{value:+.{digits}f}')} {_E(unit)}</td>"
          f"<td class=\"num\">{'–' if sigma is None else _E(f'{sigma:.{digits}f}')}</td></tr>\n")
    w("</tbody>\n</table>\n")
    if a.get("note"):
        w(f"<p class=\"note\">{_E(a['note'])}.</p>\n")
    for line in a.get("out_of_bounds") or ():
        w(f"<p class=\"out\"><b>FAIL:</b> {_E(line)}</p>\n")
    w(f"<p class=\"note\">{a.get('lenses_used', 0)} lenses; {_E(a.get('assumptions', ''))}.</p>\n")


def _measurement_section(w, measured: dict[str, Any] | None, lens_png: bytes | None, hex_: bool = False) -> None:
    """Per-lens measurements: array-wide figures and the three maps (centre x, y; focal length)."""
    w("<h2>Measured per lens</h2>\n")
    if not measured:
        w("<p>No per-lens measurements in this result.</p>\n")
        return
    s = measured["summary"]
    pct = (lambda x: "–" if x is None else f"{100 * x:+.3g} %")
    cards = [("centre RMS", "–" if s["centre_rms_um"] is None else f"{s['centre_rms_um']:.3g} µm"),
             ("centre 1σ per lens", "–" if s["centre_sigma_median_um"] is None else f"{s['centre_sigma_median_um']:.2g} µm"),
             ("median focal error", pct(s["focal_rel_median"])),
             ("focal 1σ per lens", "–" if s["focal_sigma_rel_median"] is None else f"{100 * s['focal_sigma_rel_median']:.2g} %"),
             ("focal signs known", f"{s['focal_sign_resolved']}")]
    w("<div class=\"cards\" id=\"measurements\">\n")
    for label, value in cards:
        w(f"<div class=\"card\"><b>{_E(value)}</b>{_E(label)}</div>\n")
    w("</div>\n")
    if lens_png:
        w(f"<div class=\"map\"><a href=\"{_E(REPORT_FILES['lens_maps'])}\"><img id=\"lens-maps\" alt=\"per-lens maps\" "
          f"src=\"{_data_uri(lens_png)}\"></a></div>\n")
    cells = ("One hexagonal cell per lens, U(1,1) top left, even rows (m = 2, 4, ...) half a pitch right"
             if hex_ else "One block per lens, U(1,1) top left")
    w(f"<p class=\"note\">{cells}. Centre: the optical centre's displacement in the MLA "
      f"plane against the array's typical lens (a white image alone cannot say whether pitch or a surface "
      f"decenter moved it); focal: Δf/f read from the lens' focus, f = {s['focal_length_um']:.1f} µm. Grey: not "
      f"measured (off the sensor, missing, or flagged as shifted/tilted for focal). Every value with its 1σ: "
      f"<a href=\"{_E(REPORT_FILES['csv'])}\">{_E(REPORT_FILES['csv'])}</a>.</p>\n")


def _through_focus_section(w, tf: dict[str, Any] | None) -> None:
    """The through-focus pinhole pairs, when the inspection had them: coverage, precision, pairs."""
    if not tf:
        return
    s = tf["summary"]
    sig = s.get("focal_sigma_rel_median")
    cards = [("lenses read", f"{s['lenses_covered']} ({100 * s['coverage']:.1f} %)"),
             ("pairs", f"{len(s['pairs'])}"),
             ("focal 1σ per lens", "–" if sig is None else f"{100 * sig:.2g} %"),
             ("flags read by the pairs", f"{s.get('flags_read_by_pairs', 0)}")]
    w("<h2>Through-focus pinhole frames</h2>\n<div class=\"cards\" id=\"through-focus\">\n")
    for label, value in cards:
        w(f"<div class=\"card\"><b>{_E(value)}</b>{_E(label)}</div>\n")
    w("</div>\n")
    w(f"<p class=\"note\">Each +u / −u pair of pinhole frames reads the focal-length error, with its sign, of every "
      f"lens fully lit by a pinhole (the spot grows in one frame and shrinks in the other), against the array's "
      f"typical lens. A radius defect takes the pairs' sign and the more precise of the two readings; a lens the "
      f"white frame did not flag is flagged when its reading is significant. Per lens: the tf_ columns of "
      f"<a href=\"{_E(REPORT_FILES['csv'])}\">{_E(REPORT_FILES['csv'])}</a>.</p>\n")


def _aperture_text(report: dict[str, Any]) -> str:
    """', circular lenses 90 µm across, opaque gaps' when the config says the lenses are round; else ''."""
    mla = (report.get("config") or {}).get("mla") or {}
    if not isinstance(mla, dict) or mla.get("aperture") != "circle":
        return ""
    d = mla.get("aperture_diameter_um")
    size = f" {_num(d, 4)} µm across" if isinstance(d, (int, float)) else ""
    return f", circular lenses{size}, {mla.get('gap', 'opaque')} gaps"


def _swatch(error_type: str) -> str:
    r, g, b = error_colour(error_type)
    return f"<span class=\"sw\" style=\"background:#{r:02x}{g:02x}{b:02x}\"></span>"


def _metric_medians(v: View) -> dict[str, float]:
    """Median of every index over the lenses where it is defined (NaN if nowhere)."""
    out = {}
    for name in METRICS:
        a = np.asarray(v.result.metrics[name], dtype=float)
        a = a[np.isfinite(a)]
        out[name] = float(np.median(a)) if a.size else math.nan
    return out


def _lens_card(v: View, d: Defect, medians: dict[str, float]) -> str:
    sub = np.asarray(v.subimages[d.m - 1, d.n - 1], dtype=np.float32)
    ref = np.asarray(v.reference_of(d.m, d.n), dtype=np.float32)
    both = np.concatenate([sub[np.isfinite(sub)], ref[np.isfinite(ref)]])
    lo, hi = (float(both.min()), float(both.max())) if both.size else (0.0, 1.0)
    if not hi > lo:
        hi = lo + 1.0
    side = max(sub.shape + ref.shape)
    k = max(1, min(12, math.ceil(128 / max(1, side))))
    imgs = [_data_uri(_encode_png(_grey_tile(a, lo, hi, k))) for a in (sub, ref)]
    values = v.result.metrics.at(d.m, d.n)
    parts = [f"<div class=\"lens\" id=\"U{d.m}-{d.n}\"><h3>{_swatch(d.error_type)}U({d.m},{d.n}) · "
             f"{_E(d.error_type)} · {_E(_num(d.magnitude))} {_E(d.unit)}"
             + (f" @ {_E(_num(d.direction_deg, 3))}°" if d.direction_deg is not None else "")
             + f" · {'within tolerance' if d.within_tolerance else 'OUT of tolerance'}</h3>\n<div class=\"pair\">"]
    for label, uri, a in (("lens", imgs[0], sub), ("reference", imgs[1], ref)):
        parts.append(f"<figure><img alt=\"{label} U({d.m},{d.n})\" width=\"{a.shape[1] * k}\" "
                     f"height=\"{a.shape[0] * k}\" src=\"{uri}\"><figcaption>{label}</figcaption></figure>")
    parts.append(f"</div><div class=\"note\">grey scale {_E(_num(lo, 3))} … {_E(_num(hi, 3))} · "
                 f"score {_E(_num(d.score, 3))}</div>\n")
    alts = [a for a in getattr(d, "alternatives", ()) or () if len(a) == 4]
    if alts:
        readings = "; ".join(f"{t} {_num(mag)} {u}" + (f" @ {_num(a, 3)}°" if a is not None else "")
                             for t, mag, u, a in alts)
        parts.append(f"<div class=\"note\">also fits: {_E(readings)}</div>\n")
    parts.append("<table><tr><th>index</th><th>lens</th><th>median</th><th>unit</th></tr>")
    for name, (unit, meaning) in METRICS.items():
        val = d.indexes.get(name, values.get(name, math.nan))
        parts.append(f"<tr title=\"{_E(meaning)}\"><td>{_E(name)}</td><td class=\"num\">{_E(_num(val))}</td>"
                     f"<td class=\"num\">{_E(_num(medians[name]))}</td><td>{_E(unit)}</td></tr>")
    for name in (k for k in d.indexes if k not in METRICS):
        parts.append(f"<tr><td>{_E(str(name))}</td><td class=\"num\">{_E(_num(d.indexes[name]))}</td>"
                     "<td></td><td></td></tr>")
    parts.append("</table></div>\n")
    return "".join(parts)


def _grey_tile(a: np.ndarray, lo: float, hi: float, k: int) -> np.ndarray:
    """uint8 tile of `a` on the scale lo..hi, enlarged k times by pixel repetition (NaN black)."""
    t = np.nan_to_num((a - lo) * (255.0 / (hi - lo)), nan=0.0, posinf=255.0, neginf=0.0)
    t = np.clip(t + 0.5, 0, 255).astype(np.uint8)
    return np.repeat(np.repeat(t, k, axis=0), k, axis=1)

