"""One inspection as the results database keeps it: the array-level readings and the flagged lenses of a
report (report.json's content), plus who and what it was (`Identity`)."""

from __future__ import annotations

import getpass
import hashlib
import json
import os
import socket
from dataclasses import dataclass
from typing import Any

# report.json's assembly readings -> the database's columns (value, sigma)
ASSEMBLY_COLUMNS = {
    "mla_sensor_distance_um": ("distance_um", "distance_sigma_um"),
    "mla_rotation_deg": ("mla_rotation_deg", "mla_rotation_sigma_deg"),
    "mla_tilt_x_deg": ("tilt_x_deg", "tilt_x_sigma_deg"),
    "mla_tilt_y_deg": ("tilt_y_deg", "tilt_y_sigma_deg"),
    "mla_shift_x_um": ("shift_x_um", "shift_x_sigma_um"),
    "mla_shift_y_um": ("shift_y_um", "shift_y_sigma_um"),
}
DEFECT_COLUMNS = ("m", "n", "error_type", "magnitude", "unit", "direction_deg", "score", "within_tolerance")


@dataclass(frozen=True)
class Identity:
    """Which array an inspection was of, where and by whom (None where not known)."""

    lot: str | None = None
    wafer: str | None = None
    array: str | None = None
    position: str | None = None
    station: str | None = None
    operator: str | None = None

    @classmethod
    def here(cls, lot=None, wafer=None, array=None, position=None) -> Identity:
        """With this machine's name as the station and the logged-in user as the operator."""
        try:
            user = getpass.getuser()
        except (KeyError, OSError):  # no name for this uid (a container)
            user = None
        return cls(lot, wafer, array, position, socket.gethostname(), user)


def config_text(config: dict | None) -> tuple[str | None, str | None]:
    """(hash, canonical JSON text) of a report's config; (None, None) without one."""
    if not config:
        return None, None
    text = json.dumps(config, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:20], text


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def record_from_report(report: dict) -> dict:
    """The compact record of a report (report.json's content): plain JSON types, no pixel data."""
    summary, grid = report.get("summary", {}), report.get("grid_summary", {})
    limits = report.get("detection_limit") or {}
    assembly = report.get("assembly") or {}
    fields: dict[str, Any] = {
        "inspected_utc": report.get("created_utc"), "source": report.get("source") or "",
        "verdict": report.get("verdict") or "", "software_version": report.get("mlaqc_version") or "",
        "packing": (report.get("grid") or {}).get("packing"),
        "lens_rows": summary.get("rows"), "lens_cols": summary.get("cols"),
        "found": summary.get("found"), "missing": summary.get("missing"),
        "flagged": summary.get("flagged"), "out_of_tolerance": summary.get("out_of_tolerance"),
        "pitch_x_px": _num(grid.get("pitch_x_px")), "pitch_y_px": _num(grid.get("pitch_y_px")),
        "rotation_deg": _num(grid.get("rotation_deg")), "grid_rms_px": _num(grid.get("rms_residual_px")),
        "limit_pitch_um": _num(limits.get("pitch_um")), "limit_decenter_um": _num(limits.get("decenter_um")),
        "limit_radius_rel": _num(max((v for v in (limits.get("radius_rel_pos"), limits.get("radius_rel_neg"))
                                      if isinstance(v, (int, float))), default=None)),
        "counts_json": json.dumps(summary.get("by_error_type") or {}, sort_keys=True),
    }
    for key, (value_col, sigma_col) in ASSEMBLY_COLUMNS.items():
        reading = assembly.get(key) or {}
        fields[value_col], fields[sigma_col] = _num(reading.get("value")), _num(reading.get("sigma"))
    defects = [(int(d["row"]), int(d["col"]), str(d["error_type"]), _num(d.get("magnitude")), d.get("unit") or "",
                _num(d.get("direction_deg")), _num(d.get("score")), int(bool(d.get("within_tolerance"))))
               for d in report.get("defects") or ()]
    h, text = config_text(report.get("config"))
    return {"fields": fields, "defects": defects, "config_hash": h, "config_text": text}


def run_key(record: dict, identity: Identity, report_dir: str | None) -> str:
    """What makes an inspection the same one when a batch is run again: the raw (its path, size and time),
    the config, the software, the identity and the report folder. Recording it again replaces it."""
    source = record["fields"]["source"]
    try:
        st = os.stat(source)
        stamp = f"{os.path.abspath(source)}|{st.st_size}|{st.st_mtime_ns}"
    except OSError:
        stamp = source
    parts = [stamp, record["config_hash"] or "", record["fields"]["software_version"], identity.lot or "",
             identity.wafer or "", identity.array or "", identity.position or "",
             os.path.abspath(report_dir) if report_dir else ""]
    return hashlib.sha256("\x1f".join(parts).encode()).hexdigest()
