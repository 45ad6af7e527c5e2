"""Does the frame show the optics the config describes, and how are its lenses numbered? The sub-image pitch a frame measures against the
one the config predicts (lens pitch x relay magnification / pixel, spread by (b + gap) / b for an exit pupil
b before the MLA): a reference model and signatures rendered for other optics would type defects wrongly,
so a disagreement larger than the array itself can explain is said, naming the keys that set it.
"""

from __future__ import annotations

from mlaqc.optics.config import CameraConfig
from mlaqc.optics.datasheet import telecentric

# An array's own pitch scale (replication shrinkage, a few 0.1 %) and its MLA-sensor distance (tens of µm
# over a pupil distance of tens of mm: < 0.1 %) move the sub-image pitch by less than this; a wrong relay
# magnification, pixel size or pupil distance usually by more.
PITCH_TOLERANCE = 0.01


def pitch_keys(cfg: CameraConfig) -> str:
    """The config keys that set the predicted sub-image pitch, for the warning."""
    keys = ["mla.pitch_um", "sensor.pixel_um"]
    if cfg.relay.present:
        keys.append("relay.magnification")
    ml = cfg.main_lens
    if ml.ideal and not telecentric(ml.exit_pupil_mm):
        keys.append("main_lens.exit_pupil_mm")
    elif not ml.ideal:
        keys.append("geometry.mla_distance_mm")
    return ", ".join(keys[:-1]) + " or " + keys[-1]


def pitch_notes(measured_px: float, cfg: CameraConfig) -> tuple[str, ...]:
    """A warning sentence when the measured sub-image pitch is off the config's by more than
    PITCH_TOLERANCE; nothing otherwise."""
    expected = cfg.layout.subimage_pitch_px
    off = measured_px / expected - 1.0
    if abs(off) <= PITCH_TOLERANCE:
        return ()
    return (f"WARNING: the frame's sub-image pitch is {measured_px:.3f} px but the config predicts {expected:.3f} px "
            f"({off:+.1%}), more than the array's own pitch scale or placement explains: the reference model and "
            f"signatures are for other optics, so defect types and sizes are not to be trusted; check "
            f"{pitch_keys(cfg)} (`mlaqc models -c CONFIG` prints what they give).",)


def anchoring_notes(cfg: CameraConfig) -> tuple[str, ...]:
    """How the lens indexes U(m,n) were anchored, when not to the array's corner: with count_w = count_h =
    "auto" the frame sees part of an array larger than it."""
    if not cfg.mla.counts_auto:
        return ()
    return (f"Lens indexes are relative to the frame (mla.count_w / count_h = \"auto\": {cfg.mla.count_w} x "
            f"{cfg.mla.count_h} lenses cover the sensor): U(1,1) is the top-left lens the frame cuts, not the "
            "array's corner; the lenses the frame cuts are not inspected (report.json not_inspected; a saved "
            "grid marks them clipped).",)
