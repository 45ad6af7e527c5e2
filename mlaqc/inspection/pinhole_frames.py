"""Through-focus pinhole frames from files: each raw with the `ThroughFocus` record that says how it was
taken, loaded and prepared for mlaqc.inspection.throughfocus.

The record comes from the raw's sidecar: `<raw>.sim.json` (`mlaqc simulate --scene through-focus`: key
"protocol") or `<raw>.meta.json` (`mlaqc scan` with a [through_focus] step: context.through_focus.record).
A frame from other software needs a `<raw>.meta.json` holding {"through_focus": {"focus_offset_mm": 5.0,
"f_number": 11.0, "spacing_lenses": 4, "offset_lenses": [0, 0]}} (README "File formats").
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from mlaqc.errors import InputError
from mlaqc.inspection.raw_levels import Levels, resolve_levels
from mlaqc.inspection.rawio import load_raw
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.throughfocus import ThroughFocus
from mlaqc.parallel import thread_map

if TYPE_CHECKING:
    from mlaqc.inspection.throughfocus_spots import SpotFrame

# sidecar suffix -> where the record sits in it: the simulator's; a scan's, or another program's
SIDECARS = {".sim.json": (("protocol",),), ".meta.json": (("context", "through_focus", "record"), ("through_focus",))}


def frame_record(raw: str | Path) -> ThroughFocus:
    """The ThroughFocus record of a pinhole frame, from its sidecar; InputError when it has none."""
    p = Path(raw)
    for suffix, paths in SIDECARS.items():
        side = p.with_name(p.name + suffix)
        if not side.is_file():
            continue
        try:
            doc = json.loads(side.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"sidecar {str(side)!r} of through-focus frame {str(p)!r} is not readable JSON "
                             f"({exc.__class__.__name__})") from None
        for keys in paths:
            rec = doc
            for key in keys:
                rec = rec.get(key) if isinstance(rec, dict) else None
            if isinstance(rec, dict):
                return ThroughFocus.from_dict(rec, source=f"sidecar {str(side)!r}")
    raise InputError(f"through-focus frame {str(p)!r} has no record of how it was taken: give it a "
                     f"{p.name}.meta.json sidecar with a \"through_focus\" object (focus_offset_mm, f_number, "
                     f"spacing_lenses, offset_lenses; README 'File formats')")


def load_pinhole_frames(paths: Sequence[str | Path], cfg: CameraConfig,
                        levels: Levels | None = None) -> list[tuple[SpotFrame, ThroughFocus]]:
    """Each frame prepared (`throughfocus_spots.prepare_spots`) with its record, levels settled as for the white
    frame (`pipeline.load_frame`); the analysis checks exposure itself (a pinhole frame is mostly dark).
    Frames load on a thread per core (file reads and NumPy release the GIL); uncompressed TIFFs are mapped
    (`load_raw(mapped=True)`): the analysis reads only its windows' rows, and reads them once."""
    from mlaqc.inspection.throughfocus_spots import prepare_spots

    s = cfg.sensor
    records = [frame_record(path) for path in paths]  # every sidecar checked before any raw is read

    def load(path: str | Path) -> SpotFrame:
        frame = resolve_levels(load_raw(path, expected_shape=(s.height_px, s.width_px), mapped=True), levels,
                               Levels(s.bit_depth, s.black_level_dn))
        return prepare_spots(frame)

    return list(zip(thread_map(load, list(paths)), records))
