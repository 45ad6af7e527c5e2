"""The results database as `mlaqc inspect` (and the scan and the app) use it: the --db options, and a
recorder that opens the database before the work, records each frame as its report folder is written, and
never lets a database failure cost a report: the failure is one sentence, the folders are written, and the
command ends with exit status 4 (mlaqc.resultsdb.DatabaseError) where it would have ended 0 or 1."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from mlaqc.resultsdb.record import Identity
from mlaqc.resultsdb.store import DatabaseError, default_target


def add_db_options(p: argparse.ArgumentParser, array: bool = True) -> None:
    """--db, --no-db and the array's identity (--lot, --wafer, and with `array` --array)."""
    g = p.add_argument_group("results database")
    g.add_argument("--db", metavar="TARGET",
                   help="record every inspection into this results database: an SQLite file, or a postgresql:// "
                        f"URL for one shared by several stations (default: $MLAQC_DB, else {default_target()})")
    g.add_argument("--no-db", action="store_true", help="record nothing (the report folders only)")
    g.add_argument("--lot", help="the lot the array belongs to (recorded with the inspection)")
    g.add_argument("--wafer", help="the wafer the array was cut from or sits on")
    if array:
        g.add_argument("--array", help="the array's serial or position on the wafer (one raw; a batch's frames are "
                                       "named by their position labels or raws)")


def render_with_record(result, config_dict: dict | None) -> dict:
    """A frame's report set in memory (mlaqc.report.render_report) plus "record": what the results database
    keeps of it (JSON bytes, small: it travels back from a Dask worker with the files)."""
    from mlaqc.report import render_report
    from mlaqc.resultsdb.record import record_from_report

    contents = render_report(result, config_dict, document=True)
    contents["record"] = json.dumps(record_from_report(contents.pop("document"))).encode()
    return contents


def record_from_scan_summary(summary: dict) -> dict:
    """The record of a `scan --inspect` frame from its .inspect.json summary
    (mlaqc.inspection.pipeline.scan_frame_hook: verdict, defects, grid, lattice, limits, assembly, config)."""
    from collections import Counter
    from datetime import datetime, timezone

    from mlaqc import __version__
    from mlaqc.resultsdb.record import record_from_report

    lattice, grid = summary.get("lattice") or {}, summary.get("grid") or {}
    defects = summary.get("defects") or []
    pitch = list(grid.get("pitch_px") or ()) + [None, None]
    report = {"created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "source": summary.get("source") or "", "verdict": summary.get("verdict"), "mlaqc_version": __version__,
              "grid": {"packing": lattice.get("packing")},
              "summary": {"rows": lattice.get("rows"), "cols": lattice.get("cols"), "flagged": len(defects),
                          "missing": sum(d.get("error_type") == "missing" for d in defects),
                          "out_of_tolerance": sum(not d.get("within_tolerance") for d in defects),
                          "by_error_type": dict(Counter(d.get("error_type") for d in defects))},
              "grid_summary": {"pitch_x_px": pitch[0], "pitch_y_px": pitch[1], "rotation_deg": grid.get("rotation_deg"),
                               "rms_residual_px": grid.get("rms_residual_px")},
              "detection_limit": summary.get("detection_limit"), "assembly": summary.get("assembly"),
              "config": summary.get("config"), "defects": defects}
    return record_from_report(report)


class Recorder:
    """Records frames into the results database; remembers whether any could not be."""

    def __init__(self, args: argparse.Namespace, command: str) -> None:
        self.command = command
        self.failed = False
        self.db = None
        self.recorded = 0
        self.where = ""
        self.base = Identity.here(getattr(args, "lot", None), getattr(args, "wafer", None),
                                  getattr(args, "array", None))
        if getattr(args, "no_db", False):
            return
        from mlaqc.resultsdb.store import open_database

        try:
            self.db = open_database(getattr(args, "db", None))
            self.where = self.db.where
        except DatabaseError as exc:
            self._warn(exc)

    def record(self, record: bytes | dict | None, report_dir: str | None, position: str | None = None) -> None:
        """Record one frame (`record`: the report's compact record, as report rendering makes it)."""
        if self.db is None or record is None:
            return
        rec = json.loads(record) if isinstance(record, (bytes, str)) else record
        identity = dataclasses.replace(self.base, position=position) if position else self.base
        try:
            self.db.record(rec, identity, report_dir)
            self.recorded += 1
        except DatabaseError as exc:
            self._warn(exc)
            self.close()

    def _warn(self, exc: DatabaseError) -> None:
        self.failed = True
        print(f"mlaqc {self.command}: error: {exc}; the report folders are written all the same", file=sys.stderr)

    def status(self, status: int) -> int:
        """The command's exit status: 4 where it would be 0 or 1 and a frame was not recorded."""
        return 4 if self.failed and status in (0, 1) else status

    def close(self) -> None:
        if self.db is not None:
            self.db.close()
            self.db = None
