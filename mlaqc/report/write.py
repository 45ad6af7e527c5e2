"""Write the inspection report set: report.json, lenses.csv, defect_map(.png, _small.png), lens_maps.png,
report.html.

`write_report(result, out_dir)` renders every file in memory first (`render_report`) and only then
writes them (`write_report_files`), each through a temporary file renamed over the final name
(mlaqc.atomic). If anything fails — a bad result, an encoder error, a full disk — every temporary file
is removed and files from an earlier report are left as they were. report.json is renamed last, so a
reader that finds a new report.json finds the new set beside it. The two halves are public so that the
rendering can run elsewhere (a Dask worker, `mlaqc inspect --scheduler`) and only the bytes travel to
the one process that writes them.
"""

from __future__ import annotations

import contextlib
import gc
import os
from concurrent.futures import Future
from pathlib import Path

from mlaqc.atomic import atomic_path
from mlaqc.errors import InputError
from mlaqc.inspection.results import InspectionResult
from mlaqc.parallel import cores, in_pool, pool
from mlaqc.report.document import REPORT_FILES, build_report_dict, dumps_utf8, lenses_csv_utf8
from mlaqc.report.html import _html
from mlaqc.report.lensmaps import render_lens_maps
from mlaqc.report.maps import _PNG_LEVEL, render_defect_map
from mlaqc.report.png import encode_png_async
from mlaqc.report.view import View

SMALL_MAP_MAX_PX = 1024

def write_report(result: InspectionResult, out_dir: str | os.PathLike[str], *,
                 config_dict: dict | None = None) -> dict[str, Path]:
    """Write the report set for `result` into `out_dir` (created if its parent exists).

    Returns {key: path} for the keys of REPORT_FILES. Raises InputError (one sentence) if the result
    is inconsistent or the folder cannot be written; no partial file is ever left behind.
    """
    _check_out_dir(Path(out_dir))  # before the rendering: a bad folder is refused at once
    return write_report_files(render_report(result, config_dict), out_dir)


def render_report(result: InspectionResult, config_dict: dict | None = None, *,
                  document: bool = False) -> dict:
    """Every file of the report set in memory, {key of REPORT_FILES: bytes}; nothing is written. With
    `document`, also report.json's content as a dict under "document" (read without parsing the file).

    Raises InputError (one sentence) if the result is inconsistent."""
    with _no_collection():
        contents = _render_all(View(result), config_dict)
    if not document:
        del contents["document"]
    return contents


@contextlib.contextmanager
def _no_collection():
    """The cyclic garbage collector paused: the report builds ~10^5 strings, lists and dicts and no cycles,
    and the collections they set off scanned the whole heap (30-50 ms of a 2048² frame's report)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def write_report_files(contents: dict[str, bytes], out_dir: str | os.PathLike[str]) -> dict[str, Path]:
    """Write a rendered report set (`render_report`) into `out_dir` (created if its parent exists),
    atomically, report.json last. Returns {key: path}; InputError if the folder cannot be written."""
    out = Path(out_dir)
    _check_out_dir(out)
    missing = [k for k in REPORT_FILES if k not in contents]
    if missing:
        raise InputError(f"cannot write the report: the rendered set lacks {', '.join(missing)}.")
    created = False
    try:
        try:
            out.mkdir()
            created = True
        except FileExistsError:
            pass
        with contextlib.ExitStack() as stack:
            # Entered first = renamed last: report.json marks the set as complete.
            for key in ("json", "html", "csv", "lens_maps", "defect_map_small", "defect_map"):
                tmp = stack.enter_context(atomic_path(out / REPORT_FILES[key]))
                _write_bytes(tmp, contents[key])
    except BaseException as exc:
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if still empty
        if isinstance(exc, OSError):
            reason = (exc.strerror or str(exc)).rstrip(".")
            raise InputError(f"cannot write the report to {out}: {reason}.") from exc
        raise
    return {key: out / name for key, name in REPORT_FILES.items()}


def _check_out_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"cannot write the report: {out} exists and is not a folder.")
    if not out.parent.is_dir():
        raise InputError(f"cannot write the report: folder {out.parent} does not exist.")


def _write_bytes(path: Path, data: bytes) -> None:
    """Write one temporary file (a seam for tests that simulate a full disk)."""
    path.write_bytes(data)


def _render_all(view: View, config_dict: dict | None) -> dict:
    """Every file's bytes, keyed like REPORT_FILES, and report.json's dict ("document"): lenses.csv (compiled formatting) and the PNGs' bands
    (deflate) run on the pool's threads, both releasing the GIL, while this thread draws the maps and
    builds the JSON and then the HTML."""
    csv_bytes = _in_background(lenses_csv_utf8, view, _pitch_um(config_dict))  # first: queued before the PNGs' bands
    base = view.tone_mapped()
    full = render_defect_map(view, base=base)
    small = render_defect_map(view, base=base, max_side=SMALL_MAP_MAX_PX)
    lens_maps = render_lens_maps(getattr(view.result, "measurements", None), (view.rows, view.cols),
                                 view.packing)
    full_png = encode_png_async(full, level=_PNG_LEVEL)
    small_png = encode_png_async(small, level=3) if small.shape != full.shape else full_png
    lens_png = encode_png_async(lens_maps, level=6)
    report = build_report_dict(view.result, config_dict=config_dict, _view=view)
    files = {"json": dumps_utf8(report), "csv": csv_bytes.result()}
    pngs = {"defect_map": full_png.result(), "defect_map_small": small_png.result(), "lens_maps": lens_png.result()}
    files["html"] = _html(view, report, pngs["defect_map_small"], pngs["lens_maps"]).encode("utf-8")
    return {**files, **pngs, "document": report}


def _pitch_um(config_dict: dict | None) -> float | None:
    """The config's mla.pitch_um (for a hex lenses.csv's design centres in µm), None if not given."""
    try:
        value = float(config_dict["mla"]["pitch_um"])  # type: ignore[index]
    except (KeyError, TypeError, ValueError):
        return None
    return value


def _in_background(fn, *args) -> Future:
    """fn(*args) on the process' pool (here at once in one of its own threads or on one core)."""
    if in_pool() or cores() == 1:
        done: Future = Future()
        try:
            done.set_result(fn(*args))
        except Exception as exc:  # noqa: BLE001 - re-raised by .result(), as a pool task's would be
            done.set_exception(exc)
        return done
    return pool().submit(fn, *args)
