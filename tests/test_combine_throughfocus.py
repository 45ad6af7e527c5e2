"""The white frame plus the through-focus pairs: the combination rules (mlaqc.inspection.combine) on hand-made
readings, the pinhole frames' records (mlaqc.inspection.pinhole_frames), and `mlaqc inspect --through-focus`
end to end on ray-traced frames of a seeded array."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection.combine import SOURCE_KEY, combine_through_focus
from mlaqc.inspection.pinhole_frames import frame_record
from mlaqc.inspection.results import Defect, InspectionResult, LensMetrics
from mlaqc.optics.config import QC
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.throughfocus import ThroughFocus

SMALL = str(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
QC0 = QC()  # radius tolerance 5 %, report floor 40 % of it, detect_sigma 6


def white_result(defects: list[Defect], white_sigma: float = 0.004, shape=(6, 6)) -> InspectionResult:
    flagged = np.zeros(shape, bool)
    error_type = np.full(shape, "", dtype=object)
    for d in defects:
        flagged[d.m - 1, d.n - 1] = True
        error_type[d.m - 1, d.n - 1] = d.error_type
    measurements = {"focal_sigma_rel": np.full(shape, white_sigma)}
    return InspectionResult("FAIL", None, LensMetrics({"flux": np.ones(shape)}), tuple(defects), flagged, error_type,
                            np.zeros((2, 2), np.float32), np.zeros((1, 1, 1, 1), np.float32), np.zeros((1, 1), np.float32),
                            "white.tiff", {}, {}, measurements=measurements)


def pairs(readings: dict[tuple[int, int], tuple[float, float]], shape=(6, 6)):
    """A through-focus reading: {U(m,n): (radius_rel, sigma)}; focal = radius here; the rest not covered."""
    radius = np.full(shape, np.nan)
    sigma = np.full(shape, np.nan)
    for (m, n), (r, s) in readings.items():
        radius[m - 1, n - 1], sigma[m - 1, n - 1] = r, s
    return SimpleNamespace(radius_rel=radius, focal_rel=radius, focal_sigma_rel=sigma, covered=np.isfinite(radius))


def radius_defect(m: int, n: int, mag: float, alt: float | None = None) -> Defect:
    alts = () if alt is None else (("radius", alt, "rel", None),)
    return Defect(m, n, "radius", mag, "rel", None, 9.0, abs(mag) <= 0.05, {}, alternatives=alts)


def test_the_pairs_settle_the_sign_and_the_more_precise_reading_gives_the_size():
    white = white_result([radius_defect(2, 2, 0.055, alt=-0.045), radius_defect(2, 5, 0.07, alt=-0.06),
                          radius_defect(5, 2, 0.06, alt=-0.05)])
    tf = pairs({(2, 2): (-0.05, 0.002), (2, 5): (0.08, 0.01), (5, 2): (-0.05, 0.025)})
    out = {(d.m, d.n): d for d in combine_through_focus(white, tf, QC0).defects}
    # U(2,2): pairs sure of the sign (z 25) and more precise: their reading, the white's alternative dropped
    assert out[(2, 2)].magnitude == pytest.approx(-0.05) and out[(2, 2)].alternatives == ()
    assert out[(2, 2)].within_tolerance and out[(2, 2)].indexes[SOURCE_KEY] == pytest.approx(25.0)
    # U(2,5): pairs confirm the sign (z 8) but are less precise than the white frame: the white's size
    assert out[(2, 5)].magnitude == pytest.approx(0.07) and out[(2, 5)].alternatives == ()
    # U(5,2): the pairs are not sure (z 2): the white reading stands with its alternative
    assert out[(5, 2)].magnitude == pytest.approx(0.06) and len(out[(5, 2)].alternatives) == 1


def test_a_significant_reading_the_white_frame_missed_is_flagged_and_the_verdict_follows():
    white = white_result([])
    white = white.__class__(**{**white.__dict__, "verdict": "PASS"})
    tf = pairs({(3, 3): (0.08, 0.005), (4, 4): (0.04, 0.004), (1, 6): (0.01, 0.001), (6, 6): (0.1, 0.03)})
    got = combine_through_focus(white, tf, QC0)
    flagged = {(d.m, d.n): d for d in got.defects}
    # U(3,3) z 16, 8 % > 5 %: out of tolerance; U(4,4) z 10, 4 %: within; U(1,6) 1 % is below the 2 % report
    # floor; U(6,6) z 3.3 is not significant
    assert set(flagged) == {(3, 3), (4, 4)}
    assert flagged[(3, 3)].error_type == "radius" and not flagged[(3, 3)].within_tolerance
    assert flagged[(4, 4)].within_tolerance
    assert got.verdict == "FAIL" and got.flagged[2, 2] and got.error_type[3, 3] == "radius"
    assert got.through_focus is tf
    tf_ok = pairs({(4, 4): (0.04, 0.004)})
    assert combine_through_focus(white, tf_ok, QC0).verdict == "PASS"


def test_frame_records_come_from_the_sidecars_and_their_absence_is_one_sentence(tmp_path):
    raw = tmp_path / "tf.tiff"
    raw.write_bytes(b"")
    with pytest.raises(InputError, match="has no record of how it was taken"):
        frame_record(raw)
    rec = ThroughFocus(focus_offset_mm=-5.0, offset_lenses=(2, 3))
    (tmp_path / "tf.tiff.meta.json").write_text(json.dumps({"through_focus": rec.to_dict() | {"carrier_axes_mm": {}}}))
    assert frame_record(raw) == rec
    (tmp_path / "tf.tiff.sim.json").write_text("{not json")
    with pytest.raises(InputError, match="not readable JSON"):
        frame_record(raw)
    (tmp_path / "tf.tiff.sim.json").write_text(json.dumps({"protocol": {"focus_offset_mm": "far"}}))
    with pytest.raises(InputError, match="not a through-focus frame record"):
        frame_record(raw)


def test_inspect_with_through_focus_frames_flags_and_signs_a_radius_error_at_the_cameras_best_focus(tmp_path, capsys):
    """+10 % radius sits near the Table 1 camera's best focus, where the white frame hardly sees it; the pair
    of pinhole frames whose lattice has a pinhole on that lens reads it with its sign."""
    em = ErrorMap.zeros(24, 24).with_lens(10, 10, radius_front_rel=0.10, radius_back_rel=0.10)
    em.save(tmp_path / "errs.json")
    base = ["simulate", "-c", SMALL, "-e", str(tmp_path / "errs.json"), "-q"]
    assert main(base + ["--rays-per-pixel", "200", "--out", str(tmp_path / "white.tiff")]) == 0
    frames = []
    # the first protocol on purpose (f/8, 9 lenses apart: a pinhole on lens (10, 10)) and its tuned exposure: the
    # healthy diagonal neighbour (9, 9) reads +2 % at z 5.5 here, 6.2 at the derived 2.24e6 photons (flagged)
    for u in (10, -10):
        frames.append(str(tmp_path / f"tf{u}.tiff"))
        assert main(base + ["--scene", "through-focus", "--focus-offset-mm", str(u), "--f-number", "8",
                            "--pinhole-spacing", "9", "--pinhole-photons", "2.2e6", "--out", frames[-1]]) == 0
    code = main(["inspect", str(tmp_path / "white.tiff"), "-c", SMALL, "-t", *frames, "-o", str(tmp_path / "rep")])
    err = capsys.readouterr().err
    assert code == 1 and "through-focus:" in err
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    d = {(x["row"], x["col"]): x for x in report["defects"]}
    assert d[(10, 10)]["error_type"] == "radius" and d[(10, 10)]["magnitude"] > 0.05
    assert d[(10, 10)]["indexes"][SOURCE_KEY] > 6
    assert len(d) == 1  # no healthy lens flagged
    tf = report["through_focus"]
    assert tf["summary"]["flags_read_by_pairs"] == 1 and tf["summary"]["lenses_covered"] > 0
    assert tf["lenses"]["tf_radius_rel"][9][9] > 0.05  # +10 %: positive errors read low at u = ±10 mm (bench)
    rows = (tmp_path / "rep" / "lenses.csv").read_text().splitlines()
    header = rows[0].split(",")
    lens = dict(zip(header, rows[1 + 9 * 24 + 9].split(",")))
    assert float(lens["tf_focal_sigma_rel"]) > 0 and lens["row"] == "10" and lens["col"] == "10"
    assert 'id="through-focus"' in (tmp_path / "rep" / "report.html").read_text()
    # a pinhole frame given as a batch member, or without a record: one sentence, exit 2, no report
    assert main(["inspect", str(tmp_path / "white.tiff"), str(tmp_path / "white.tiff"), "-c", SMALL, "-t", frames[0],
                 "-o", str(tmp_path / "rep2")]) == 2
    assert main(["inspect", str(tmp_path / "white.tiff"), "-c", SMALL, "-t", str(tmp_path / "white.tiff"),
                 "-o", str(tmp_path / "rep3")]) == 2
    assert not (tmp_path / "rep3").exists()
    assert "has no record" in capsys.readouterr().err
