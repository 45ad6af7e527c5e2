"""The through-focus pinhole protocol: the second measurement that reads each microlens' focal length
with its sign (bench/type_separation.py chose it; README "What a frame can carry").

A plate of pinholes sits where the white target was, the main lens is stopped to f/N, and the plate is
moved along the optical axis (stage Z) so the main lens images the pinholes `focus_offset_mm` (u) behind
(+) or in front of (-) the MLA. Each pinhole then lights a disc on the MLA (`blur_radius_mm`, traced:
0.115 mm at u = +5 mm and 0.161 mm at u = -5 mm for Table 1 at f/11, 1.2 / 1.6 lens pitches, so the
discs of pinholes 4 lenses apart stay apart; paraxially (D_N / 2) |u| / (b + u), 0.131 / 0.139 mm, but
the main lens' spherical aberration moves the marginal focus), and every lenslet fully inside it sees a
nearly spherical wave of vergence 1/u and focuses it to a spot on the sensor (a Shack-Hartmann sensor). A
lens' own focus error grows the spot in one frame of the +u / -u pair and shrinks it in the other, so
the pair carries the sign at first order.

The shipped protocol (`FOCUS_OFFSET_MM`, `F_NUMBER`, `SPACING_LENSES`: the Carrier, the scan plan's
[through_focus] table, the mock camera's mask and `mlaqc simulate --scene through-focus`) is u = ±5 mm at
f/11 with pinholes 4 lenses apart: 16 lattice offsets, 32 frames to cover the array, and every seeded
±3/5/10 % focal error sized within 15 % (120 of 120 over seeds 2-6; README, bench/throughfocus_accuracy.py;
at ±10 mm the spots are about a pixel and 58 of 72 are). `ThroughFocus`'s own field defaults are still the first
protocol's (10 mm, f/8, 9 lenses): tests/test_throughfocus_analysis.py builds its frames on them.

The pinholes' images form a square lattice `spacing_lenses` lens pitches apart, shifted by
`offset_lenses` (x, y) lens pitches; `coverage_offsets` lists the lattice shifts that put every lens
fully inside some disc. On a hex array (mla.packing = "hex") the pinholes sit on the hex sub-lattice of
step s = `spacing_lenses`: lens steps s a1 and s a2 with a1 = (1, 0) (along a row) and a2 = (1/2, sqrt(3)/2)
(one row down, half a pitch right), i.e. s lenses along a row and s rows down with s/2 pitches of x; every
pinhole has 6 pinhole neighbours s pitches away, as its lens has 6 lens neighbours one pitch away.
`offset_lenses` = (q, r) then shifts that sub-lattice by q a1 + r a2 ("axial" lens steps: lens (row,
col) has q = col - row // 2, 0-based), and the s^2 offsets 0 <= q, r < s are its s^2 distinct cosets,
as the s^2 (x, y) offsets are on a square array (`pinhole_lenses`).

Lens (row r, col c) of a square array has its design centre at x = (c - (cols - 1) / 2) p,
y = (r - (rows - 1) / 2) p on the MLA (camera frame: x right, y down; hex: `Lattice.position`); the main
lens inverts, so an object point at -x / m images at x.

`photons_per_pinhole` defaults to None: the protocol's exposure, `pinhole_photons(cfg, tf)`, derived from
the optics rather than tuned. `spot_peak_per_photon` traces the pinhole nearest the axis (and the lattice
neighbours whose discs can reach the same lenses) through the stopped main lens and the design MLA to the
sensor, bins the spots at every sub-pixel phase, applies the formation model's PSF (diffraction,
crosstalk) and takes the best-phased brightest pixel; `pinhole_photons` then sets the brighter frame of
the +|u| / -|u| pair to `FILL_FRACTION` (50 %: room for the focused spots of defective lenses) of full
well at the sensor's QE, whatever u, the f-number or the spacing are, and the other frame falls where the
optics put it. Table 1 (QE 0.6, full well 20,000 e-): 2.63e5 photons at ±5 mm f/11, the -5 mm frame the
brighter (6.3 % / 3.5 % of a pinhole's photons in the brightest pixel at -5 / +5 mm, so +5 mm peaks
near 28 %); 1.39e6 at ±10 mm f/8 (the +10 mm frame; the first protocol's constant, tuned for 80 %, was
2.2e6 = 1.39e6 x 0.8 / 0.5). Rendered frames land within a few % of that (`mlaqc simulate --no-noise`,
default rays; measured at 80 %: the whole Table 1 frame 81.3 % / 44.9 % of full well at -5 / +5 mm, 676
spots; PRNU and the render's noise add about 1 %; the 24 x 24 small camera 76.5 % / 44.6 %, 36 spots hold
fewer sub-pixel phases); tests/test_throughfocus_acquire.py checks the small camera. The photons scale
linearly: 2.63e5 into the f/11 pupil per 10 ms is about 8 pW per pinhole at 633 nm. The target is the
healthy array's: a lens whose focal error brings one frame's focus near the sensor gathers its spot into
a pixel or two and peaks up to 1.75x higher (the FILL_FRACTION note), still under full well at 50 %;
mlaqc.inspection.throughfocus leaves a lens with a saturated spot out of that pair.

The bench (`Carrier`): the pinholes are a backlit chrome-on-glass mask on the stage's auxiliary axes Z
(along the optical axis, +Z away from the camera) and A, B (across it, +A along the camera's +x, +B
along +y). Along B the mask holds a clear window (field 0: the backlight's diffuser fills the view, the
white frame) and one pinhole lattice per focus offset (field k), each drawn at the object pitch that
images to `spacing_lenses` lens pitches at its own u (the magnification differs by 9 % between
u = +5 and -5 mm, 18 % between ±10 mm, so one lattice cannot serve both). `carrier_axes` gives the Z, A,
B of a frame; `carrier_view` turns stage readings back into what the camera sees (the mock camera
renders that).
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.optics.config import CameraConfig, require_thick_main_lens
from mlaqc.optics.lattice import SQRT3_2, Lattice, hex_cell
from mlaqc.optics.paraxial import image_distance
from mlaqc.optics.scene import PointScene, Scene, WhiteScene

PROTOCOL = "through-focus"
FOCUS_OFFSET_MM = 5.0  # the shipped protocol: pinholes imaged ±5 mm from the MLA ...
F_NUMBER = 11.0  # ... through the main lens stopped to f/11 ...
SPACING_LENSES = 4  # ... 4 lens pitches apart (16 lattice offsets: 32 frames cover the array)
# The default exposure puts the pair's brightest healthy spot pixel at this fraction of full well. A lens
# whose focal error brings its spot into focus peaks up to 1.75x higher (traced on the small camera at
# ±5 mm f/11: radius +8 to +14 % at +5 mm, -4 to -8 % at -5 mm), and a clipped spot cannot be read; at
# 0.5 those stay under 0.9 of full well, for 1.26x the shot noise of 0.8 (healthy sd 0.09 -> ~0.12 %).
FILL_FRACTION = 0.5


@dataclass(frozen=True)
class ThroughFocus:
    """One frame of the protocol: where the pinholes' image lies and how the lattice sits. The field
    defaults are the first protocol's (see the module docstring); the shipped one is FOCUS_OFFSET_MM,
    F_NUMBER, SPACING_LENSES."""

    focus_offset_mm: float = 10.0  # u: paraxial image of the pinholes this far behind (+) / in front of (-) the MLA
    f_number: float = 8.0  # main lens stopped to efl / N
    spacing_lenses: int = 9  # pinhole images this many lens pitches apart on the MLA
    offset_lenses: tuple[int, int] = (0, 0)  # shift of the lattice in lens steps: square (x, y), hex axial (q, r)
    photons_per_pinhole: float | None = None  # photons each pinhole sends into the pupil; None: `pinhole_photons`

    def __post_init__(self) -> None:
        if not (math.isfinite(self.focus_offset_mm) and abs(self.focus_offset_mm) >= 0.5):
            raise InputError(f"through-focus offset must be a finite distance of at least 0.5 mm, not {self.focus_offset_mm!r}")
        if not (math.isfinite(self.f_number) and self.f_number >= 1.0):
            raise InputError(f"through-focus f-number must be at least 1, not {self.f_number!r}")
        if int(self.spacing_lenses) != self.spacing_lenses or self.spacing_lenses < 2:
            raise InputError(f"pinhole spacing must be a whole number of lenses >= 2, not {self.spacing_lenses!r}")
        if self.photons_per_pinhole is not None and not (math.isfinite(self.photons_per_pinhole)
                                                         and self.photons_per_pinhole > 0):
            raise InputError(f"photons per pinhole must be positive, not {self.photons_per_pinhole!r}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (sidecars, scan manifests, report.json)."""
        return {"protocol": PROTOCOL} | asdict(self) | {"offset_lenses": list(self.offset_lenses)}

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "record") -> ThroughFocus:
        """Inverse of `to_dict`; a malformed record is one InputError naming `source`. The focus offset,
        f-number and spacing must all be stated: a frame read with another protocol's value is read wrong."""
        missing = [k for k in ("focus_offset_mm", "f_number", "spacing_lenses") if not isinstance(d, dict) or k not in d]
        if missing:
            raise InputError(f"{source} is not a through-focus frame record (it does not state {', '.join(missing)})")
        try:
            kw = {k: d[k] for k in ("focus_offset_mm", "f_number", "spacing_lenses")}
            kw["offset_lenses"] = tuple(int(v) for v in d.get("offset_lenses", (0, 0)))
            if len(kw["offset_lenses"]) != 2:
                raise ValueError("offset_lenses needs two values")
            if d.get("photons_per_pinhole") is not None:
                kw["photons_per_pinhole"] = float(d["photons_per_pinhole"])
            return cls(**kw)
        except (TypeError, ValueError, KeyError) as exc:
            raise InputError(f"{source} is not a through-focus frame record ({exc})") from None


def stopped(cfg: CameraConfig, f_number: float) -> CameraConfig:
    """The config with its distances frozen and the main lens' rim cut to f/N (N = efl / D)."""
    c = frozen(cfg)
    return replace(c, main_lens=replace(c.main_lens, diameter_mm=c.layout.main.efl / f_number))


def frozen(cfg: CameraConfig) -> CameraConfig:
    """The config with its f-number-matched distances written into cfg.geometry, so that stopping down
    (or moving the object) does not move the MLA."""
    lay = cfg.layout
    return replace(cfg, geometry=replace(cfg.geometry, object_distance_mm=lay.object_distance_mm,
                                         mla_distance_mm=lay.mla_distance_mm))


def object_for_image_offset(cfg: CameraConfig, u_mm: float) -> CameraConfig:
    """Move the object (MLA fixed) so the main lens' paraxial image lies u_mm behind (+) the MLA."""
    lay = cfg.layout
    b = lay.mla_distance_mm + lay.main.rear_principal + u_mm
    a = image_distance(lay.main.efl, b)
    return replace(cfg, geometry=replace(cfg.geometry, object_distance_mm=a - lay.main.front_principal))


def magnification(cfg: CameraConfig) -> float:
    """|image / object| from the object plane to the MLA (paraxial, b / a)."""
    lay = cfg.layout
    return lay.pupil_to_mla_mm / (lay.object_distance_mm + lay.main.front_principal)


def frame_config(cfg: CameraConfig, tf: ThroughFocus) -> CameraConfig:
    """The camera of a through-focus frame: `cfg` stopped to f/N with the object moved to give offset u
    (InputError for an ideal main lens: the pinholes are traced through its surfaces)."""
    require_thick_main_lens(cfg, "a through-focus frame (pinholes imaged through the main lens)")
    return object_for_image_offset(stopped(cfg, tf.f_number), tf.focus_offset_mm)


def stage_z_mm(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """How far the pinhole plate sits from the white target's plane (+ = away from the camera)."""
    return frame_config(cfg, tf).layout.object_distance_mm - cfg.layout.object_distance_mm


def focus_offset_at_stage_z(cfg: CameraConfig, stage_z: float) -> float:
    """Inverse of `stage_z_mm`: the focus offset u (mm) of a target `stage_z` mm from the white target's
    plane (+ = away from the camera); independent of the f-number (stopping down keeps the distances)."""
    lay = frozen(cfg).layout
    a = lay.object_distance_mm + stage_z + lay.main.front_principal
    if not (math.isfinite(a) and a > lay.main.efl):
        raise InputError(f"a target {stage_z:+.3f} mm from the white target's plane is at or inside the main lens' "
                         "focal length: the camera forms no real image of it")
    return image_distance(lay.main.efl, a) - lay.mla_distance_mm - lay.main.rear_principal


def blur_radius_mm(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """Radius (mm) of the disc one pinhole lights on the MLA: the height there of the on-axis pinhole's
    marginal ray, traced through the stopped main lens (its edge: no light falls beyond it).

    The paraxial estimate `paraxial_blur_radius_mm` misses two things the real lens does: the stop is
    the rim at the front vertex, not a disc at the principal plane (+2 %), and spherical aberration
    brings the marginal rays to focus about 0.8 mm short of the paraxial image at f/8, so the disc is
    12 % smaller at u = +10 mm (0.310 mm) and 14 % larger at u = -10 mm (0.450 mm) for Table 1. It is
    not uniformly lit either (a bright rim at +u, a dim one at -u). tests/test_throughfocus_acquire.py
    recovers this edge within 1 % from rendered frames."""
    from mlaqc.optics.raytrace import MainLens, Rays

    c = frame_config(cfg, tf)
    lens, lay = MainLens(c), c.layout
    z0 = lay.z_object_mm

    def trace(rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Heights at the MLA plane of rays from the on-axis pinhole aimed at height rho on the front vertex
        plane, and whether they pass."""
        n = len(rho)
        norm = np.sqrt(rho * rho + z0 * z0)
        r = Rays(np.zeros(n), np.zeros(n), np.full(n, z0), rho / norm, np.zeros(n), -z0 / norm, np.ones(n))
        lens.trace(r)
        t = (lay.z_mla_mm - r.z) / r.N
        return np.abs(r.x + t * r.L), r.w > 0

    lo, hi = 0.0, 0.75 * c.main_lens.diameter_mm  # aim heights: lo passes, hi (beyond the rim) does not
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if trace(np.array([mid]))[1][0] else (lo, mid)
    h, ok = trace(np.linspace(0.0, lo, 65))
    return float(np.max(h[ok]))


def paraxial_blur_radius_mm(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """The paraxial disc radius (D_N / 2) |u| / (b + u): the stopped aperture D_N = efl / N taken at the
    rear principal plane, b from there to the MLA (0.352 / 0.394 mm at u = +10 / -10 mm, Table 1 f/8)."""
    c = frame_config(cfg, tf)
    b = c.layout.pupil_to_mla_mm + tf.focus_offset_mm
    return 0.5 * c.main_lens.diameter_mm * abs(tf.focus_offset_mm) / b


def inner_radius_lenses(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """Distance (lens pitches) from a disc's centre within which a whole lens aperture is lit."""
    corner = 1.0 / math.sqrt(3.0) if cfg.mla.packing == "hex" else math.sqrt(0.5)  # the cell's farthest point
    return blur_radius_mm(cfg, tf) / (cfg.mla.pitch_um * 1e-3) - corner


RIM_MARGIN_LENSES = 0.15  # a lens counts as fully lit this far inside the disc's traced rim


def pair_radius_lenses(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """How far (lens pitches) from its pinhole a lens is read: fully lit, with RIM_MARGIN_LENSES to spare,
    in both frames of the +u / -u pair (the smaller disc decides)."""
    return _pair_radius(cfg, abs(tf.focus_offset_mm), tf.f_number)


@functools.lru_cache(maxsize=32)
def _pair_radius(cfg: CameraConfig, u_mm: float, f_number: float) -> float:
    tf = ThroughFocus(focus_offset_mm=u_mm, f_number=f_number)
    return min(inner_radius_lenses(cfg, replace(tf, focus_offset_mm=u)) for u in (u_mm, -u_mm)) - RIM_MARGIN_LENSES


def pinhole_lenses(cfg: CameraConfig, tf: ThroughFocus) -> np.ndarray:
    """(n, 2) int array of (row, col): the lenses at the centres of the lit discs, inside the array, row-major.
    Square: rows and columns = offset (mod s); hex: the sub-lattice of the module docstring, axial
    q = col - row // 2 = offset[0] and row = offset[1] (mod s)."""
    s, (ox, oy) = tf.spacing_lenses, tf.offset_lenses
    if cfg.mla.packing == "hex":
        r, c = np.meshgrid(np.arange(cfg.mla.count_h), np.arange(cfg.mla.count_w), indexing="ij")
        on = ((r - oy) % s == 0) & ((c - r // 2 - ox) % s == 0)
        return np.argwhere(on).astype(np.int64)
    rows = np.arange(oy % s, cfg.mla.count_h, s)
    cols = np.arange(ox % s, cfg.mla.count_w, s)
    r, c = np.meshgrid(rows, cols, indexing="ij")
    return np.stack([r.ravel(), c.ravel()], axis=1)


def lens_centres_mm(cfg: CameraConfig, rc: np.ndarray) -> np.ndarray:
    """Design centres (x, y) mm on the MLA of lenses given as (row, col) rows (off the array too): the
    lattice's (mlaqc.optics.lattice; hex rows p sqrt(3)/2 apart, odd 0-based rows shifted p/2)."""
    if cfg.mla.packing != "square":
        x, y = Lattice.of(cfg).position(rc[:, 0], rc[:, 1])
        return np.stack([x, y], axis=1)
    p = cfg.mla.pitch_um * 1e-3
    x = (rc[:, 1] - 0.5 * (cfg.mla.count_w - 1)) * p
    y = (rc[:, 0] - 0.5 * (cfg.mla.count_h - 1)) * p
    return np.stack([x, y], axis=1)


def sub_lattice_steps(packing: str, reach: float) -> list[tuple[int, int]]:
    """Steps (i, j) of the pinhole lattice (square: i rows and j columns of s; hex: i s a1 + j s a2) whose
    length, in units of s, is below `reach` (the set is symmetric: the order of i and j does not matter)."""
    if packing == "hex":
        k = int(math.floor(reach / SQRT3_2)) + 1  # |i a1 + j a2| >= sqrt(3)/2 max(|i|, |j|)
        return [(i, j) for i in range(-k, k + 1) for j in range(-k, k + 1) if math.sqrt(i * i + j * j + i * j) < reach]
    k = int(math.floor(reach))
    return [(i, j) for i in range(-k, k + 1) for j in range(-k, k + 1) if math.hypot(i, j) < reach]


def sub_lattice_lenses(cfg: CameraConfig, lens: tuple[int, int], s: int, steps: list[tuple[int, int]]) -> np.ndarray:
    """(n, 2) (row, col) of the pinhole-lattice points `steps` (see `sub_lattice_steps`) from lens (row, col),
    off the array too."""
    st = np.array(steps, dtype=np.int64).reshape(-1, 2)
    r0, c0 = lens
    if cfg.mla.packing == "hex":
        r = r0 + s * st[:, 1]
        q = (c0 - r0 // 2) + s * st[:, 0]
        return np.stack([r, q + r // 2], axis=1)
    return np.array([r0, c0]) + s * st


def axial_shift_lenses(packing: str, offset: tuple[float, float]) -> tuple[float, float]:
    """(x, y) lens pitches of a pinhole-lattice offset: square (x, y) itself, hex q a1 + r a2."""
    if packing == "hex":
        q, r = offset
        return q + 0.5 * r, SQRT3_2 * r
    return float(offset[0]), float(offset[1])


def scene(cfg: CameraConfig, tf: ThroughFocus) -> PointScene:
    """The pinhole plate of this frame: object points whose paraxial images land on the lattice lenses, each
    sending `tf.photons_per_pinhole` (None: `pinhole_photons(cfg, tf)`) into the pupil."""
    m = magnification(frame_config(cfg, tf))
    img = lens_centres_mm(cfg, pinhole_lenses(cfg, tf))
    photons = pinhole_photons(cfg, tf) if tf.photons_per_pinhole is None else tf.photons_per_pinhole
    return PointScene(points_mm=tuple((-float(x) / m, -float(y) / m) for x, y in img), photons=photons)


def pinhole_photons(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """The protocol's exposure: photons each pinhole sends into the pupil so that the brightest spot pixel of
    the brighter frame of the +|u| / -|u| pair (same f-number and spacing) holds FILL_FRACTION of full well
    (`spot_peak_per_photon`; the QE of the sensor's most sensitive pixels). The same for both frames of a
    pair, as one backlit mask gives; the lattice offset does not matter."""
    return _pinhole_photons(cfg, abs(float(tf.focus_offset_mm)), float(tf.f_number), int(tf.spacing_lenses))


@functools.lru_cache(maxsize=32)
def _pinhole_photons(cfg: CameraConfig, u_mm: float, f_number: float, spacing: int) -> float:
    s = cfg.sensor
    qe = max(s.cfa_qe) if s.cfa != "none" else s.qe
    peak = max(spot_peak_per_photon(cfg, ThroughFocus(u, f_number, spacing, photons_per_pinhole=1.0))
               for u in (u_mm, -u_mm))
    if not peak > 0:
        raise InputError(f"no pinhole light reaches the sensor at u = ±{u_mm:g} mm, f/{f_number:g}: no exposure can "
                         "be derived for this protocol; check the camera config and the focus offset")
    return FILL_FRACTION * s.full_well_e / (qe * peak)


PEAK_PUPIL_GRID = 256  # pupil samples per side (a polar grid, uniform in area) of each traced pinhole
PEAK_PHASES = 16  # sub-pixel phases per axis at which the spots are binned (8: 1 % lower peaks)


def spot_peak_per_photon(cfg: CameraConfig, tf: ThroughFocus) -> float:
    """Expected photons in a frame's brightest pixel per photon a pinhole sends into the pupil, after the
    image formation model's PSF (diffraction, crosstalk; PRNU and noise left out).

    The lattice pinhole nearest the axis is traced, with the light of every lattice neighbour whose disc
    reaches a lens its own disc lights (their spots can share a sub-image when the discs nearly touch;
    this is where the spacing enters; by the lattice's symmetry those lenses stand for all), from a
    deterministic pupil grid (weights as the renderer's: cos^3, Fresnel and vignetting losses) through
    the stopped main lens and the design MLA to the sensor. The spots are binned at PEAK_PHASES^2
    sub-pixel shifts of the pixel grid, each put through the PSF, and the brightest pixel of the
    best-phased binning is returned: a frame holds spots at many phases (the sub-image pitch is not a
    whole number of pixels), so its brightest pixel reads about this, PRNU and render noise aside, a few
    % less where no spot falls near the best phase. Independent of the lattice offset; a fraction of a
    second for the shipped protocol, seconds where discs overlap widely (`pinhole_photons` caches its
    answer per camera and protocol)."""
    import cv2

    from mlaqc.optics.formation import formation_kernels
    from mlaqc.optics.raytrace import Camera, Rays
    from mlaqc.optics.render import source_region
    from mlaqc.optics.scene import sample_points

    fc = frame_config(cfg, tf)
    cam = Camera(fc)
    region = source_region(cam)
    m = magnification(fc)
    p = cfg.mla.pitch_um * 1e-3
    s = int(tf.spacing_lenses)
    centre = (cfg.mla.count_h // 2, cfg.mla.count_w // 2)
    radius = blur_radius_mm(cfg, tf)
    corner = 2.0 / math.sqrt(3.0) if cfg.mla.packing == "hex" else math.sqrt(2.0)  # twice the cell's corner
    lit = radius + corner * p  # the lenses a disc lights lie within this of its centre
    reach = (lit + radius) / (s * p)  # in lattice steps
    steps = sub_lattice_steps(cfg.mla.packing, reach)
    img = lens_centres_mm(cfg, sub_lattice_lenses(cfg, centre, s, steps))  # off the array too: a neighbour's light
    cx, cy = img[steps.index((0, 0))]
    g = (np.arange(PEAK_PUPIL_GRID) + 0.5) / PEAK_PUPIL_GRID
    u = np.stack(np.meshgrid(g, g, indexing="ij")).reshape(2, -1)
    xs, ys, ws = [], [], []
    for step, (x, y) in zip(steps, img):
        r = sample_points(region, u, -float(x) / m, -float(y) / m)
        cam.trace_to_mla(r)
        if step != (0, 0):  # a neighbour: only its light on the lenses the centre disc lights
            t = (cam.z_mla - r.z) / r.N
            on = (r.w > 0) & (np.hypot(r.x + t * r.L - cx, r.y + t * r.M - cy) <= lit)
            r = Rays(*(a[on] for a in (r.x, r.y, r.z, r.L, r.M, r.N, r.w)))
        cam.trace_behind_main(r)
        ok = r.w > 0
        xs.append((r.x[ok] - cam.sx0) * cam.inv_pixel)
        ys.append((r.y[ok] - cam.sy0) * cam.inv_pixel)
        ws.append(r.w[ok] / u.shape[1])
    px, py, w = np.concatenate(xs), np.concatenate(ys), np.concatenate(ws)
    if not len(w):
        return 0.0
    psf = formation_kernels(fc, (1, 1), with_prnu=False).psf
    q, reach = PEAK_PHASES, psf.shape[0] // 2 + 2  # a pixel after the PSF gathers the rays binned this near it
    x0, y0 = math.floor(px.min()) - reach, math.floor(py.min()) - reach
    nx, ny = math.ceil(px.max()) + reach + 1 - x0, math.ceil(py.max()) + reach + 1 - y0
    col, row = np.floor(px - x0).astype(np.int64), np.floor(py - y0).astype(np.int64)

    def blurred(img: np.ndarray) -> np.ndarray:
        return cv2.filter2D(img, -1, psf[::-1, ::-1], borderType=cv2.BORDER_CONSTANT) if psf.shape != (1, 1) else img

    raw = np.bincount(row * nx + col, w, minlength=ny * nx).reshape(ny, nx)
    best = float(blurred(raw).max())  # phase 0; other phases only where the light nearby could beat it
    size = (2 * reach + 1, 2 * reach + 1)
    near = cv2.boxFilter(raw, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    zone = cv2.dilate((near >= best).astype(np.uint8), np.ones(size, np.uint8))
    count, labels = cv2.connectedComponents(zone)
    for lab in range(1, count):
        rr, cc = np.nonzero(labels == lab)
        r0, c0 = rr.min(), cc.min()
        h, wd = rr.max() + 2 - r0, cc.max() + 2 - c0  # one pixel more: a shifted grid moves rays by up to one
        sel = (row >= r0) & (row < r0 + h - 1) & (col >= c0) & (col < c0 + wd - 1)
        fy = np.floor((py[sel] - y0 - r0) * q).astype(np.int64)
        fx = np.floor((px[sel] - x0 - c0) * q).astype(np.int64)
        fine = np.bincount(fy * (wd * q) + fx, w[sel], minlength=h * q * wd * q).reshape(h * q, wd * q)
        # box[y, x]: the pixel whose top-left corner is fine cell (y, x), i.e. every pixel at every phase
        box = cv2.boxFilter(fine, -1, (q, q), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
        for dy in range(q):
            for dx in range(q):
                best = max(best, float(blurred(np.ascontiguousarray(box[dy::q, dx::q][:h, :wd])).max()))
    return best


def coverage_offsets(cfg: CameraConfig, tf: ThroughFocus) -> list[tuple[int, int]]:
    """Lattice shifts (`offset_lenses`) that put every lens fully inside some lit disc: a square
    sub-lattice of step t with t / sqrt(2) <= the inner radius (the farthest a lens can be from its
    nearest pinhole), within `pair_radius_lenses` (what the analysis reads) of both frames of the +u / -u
    pair. Hex: the same grid of axial steps, t from the hex covering radius (t / sqrt(3) <= the radius),
    made smaller until every lens of the array is checked within the radius of a pinhole on the array
    (`_hex_covers`: the hex array's edges are not the sub-lattice's, so an edge lens can need a finer set).
    Empty when a disc cannot hold a whole lens (|u| too small for f/N)."""
    r_in = pair_radius_lenses(cfg, tf)
    if r_in < 0:
        return []
    s = tf.spacing_lenses
    if cfg.mla.packing == "hex":
        for t in range(max(1, min(s, int(math.floor(r_in * math.sqrt(3.0))))), 0, -1):
            steps = sorted({min(k * t, s - 1) for k in range(math.ceil(s / t))})
            offsets = [(ox, oy) for oy in steps for ox in steps]
            if _hex_covers(cfg, tf, offsets, r_in):
                return offsets
        return []
    t = max(1, min(s, int(math.floor(r_in * math.sqrt(2.0)))))
    n = math.ceil(s / t)
    steps = sorted({min(k * t, s - 1) for k in range(n)})
    return [(ox, oy) for oy in steps for ox in steps]


def _hex_covers(cfg: CameraConfig, tf: ThroughFocus, offsets: list[tuple[int, int]], r_in: float) -> bool:
    """Whether every lens of the array lies within r_in pitches (Lattice positions) of a pinhole of some
    offset, counting only the pinholes on the array (an edge lens' nearest lattice point may lie off it)."""
    from scipy.spatial import cKDTree

    lat = Lattice(cfg.mla.packing, cfg.mla.count_h, cfg.mla.count_w)
    x, y = lat.centres()
    pts = np.stack([x.ravel(), y.ravel()], axis=1)
    best = np.full(len(pts), np.inf)
    for off in offsets:
        pins = pinhole_lenses(cfg, replace(tf, offset_lenses=off))
        if len(pins):
            px, py = lat.position(pins[:, 0], pins[:, 1])
            best = np.minimum(best, cKDTree(np.stack([px, py], axis=1)).query(pts)[0])
    return bool(np.all(best <= r_in + 1e-9))


# --------------------------------------------------------------------------------------------- the bench


@dataclass(frozen=True)
class Carrier:
    """The pinhole mask on the stage's auxiliary axes (machine coordinates, mm); see the module docstring.

    Field k along B is centred at B = b_window_mm + k * field_pitch_mm: k = 0 the clear window (white
    frames), k >= 1 the lattice made for focus offset `focus_offsets_mm[k - 1]` and `spacing_lenses`.
    Z = z_white_mm puts the mask in the white target's plane; A = a_centre_mm centres the lattices
    (lattice offset 0, 0). The defaults are the shipped protocol (±5 mm, lattices 4 lenses apart; f/11 is
    the iris', set at the camera). The default field pitch leaves each field 25 mm of glass, more than
    the Table 1 camera's object field plus the largest lattice offset: 15.6 mm + 0.46 mm at u = -5 mm
    (14.4 + 0.42 mm at +5 mm; for the first protocol 16.4 + 1.3 mm at u = -10 mm)."""

    focus_offsets_mm: tuple[float, ...] = (FOCUS_OFFSET_MM, -FOCUS_OFFSET_MM)
    spacing_lenses: int = SPACING_LENSES
    z_white_mm: float = 50.0
    a_centre_mm: float = 10.0
    b_window_mm: float = 0.0
    field_pitch_mm: float = 25.0

    def __post_init__(self) -> None:
        offs = tuple(float(u) for u in self.focus_offsets_mm)
        object.__setattr__(self, "focus_offsets_mm", offs)
        if not offs or any(not (math.isfinite(u) and abs(u) >= 0.5) for u in offs) or len(set(offs)) != len(offs):
            raise InputError(f"pinhole mask focus offsets {list(offs)} must be distinct finite distances of at least 0.5 mm")
        if int(self.spacing_lenses) != self.spacing_lenses or self.spacing_lenses < 2:
            raise InputError(f"pinhole mask spacing must be a whole number of lenses >= 2, not {self.spacing_lenses!r}")
        for name in ("z_white_mm", "a_centre_mm", "b_window_mm", "field_pitch_mm"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"pinhole mask {name} must be a finite number, not {getattr(self, name)!r}")
        if self.field_pitch_mm <= 0:
            raise InputError(f"pinhole mask field_pitch_mm must be positive, not {self.field_pitch_mm!r}")

    def field_of(self, tf: ThroughFocus) -> int:
        """The field (1-based, along B) holding the lattice of this frame; InputError if the mask has none."""
        if tf.spacing_lenses != self.spacing_lenses:
            raise InputError(f"the pinhole mask's lattices are {self.spacing_lenses} lenses apart, not {tf.spacing_lenses}")
        for k, u in enumerate(self.focus_offsets_mm, start=1):
            if abs(u - tf.focus_offset_mm) <= 1e-9:
                return k
        raise InputError(f"the pinhole mask has no lattice for a focus offset of {tf.focus_offset_mm:g} mm (its lattices: "
                         f"{', '.join(f'{u:g}' for u in self.focus_offsets_mm)} mm)")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self) | {"focus_offsets_mm": list(self.focus_offsets_mm)}


def carrier_axes(cfg: CameraConfig, carrier: Carrier, tf: ThroughFocus) -> dict[str, float]:
    """Stage Z, A, B (mm) that put the mask where frame `tf` needs it: Z from `stage_z_mm`, the lattice
    field on B, and the lattice offset as an object-side shift of -offset * p / m (the image is inverted)."""
    k = carrier.field_of(tf)
    m = magnification(frame_config(cfg, tf))
    p = cfg.mla.pitch_um * 1e-3
    ox, oy = axial_shift_lenses(cfg.mla.packing, tuple(o % tf.spacing_lenses for o in tf.offset_lenses))
    return {"z": carrier.z_white_mm + stage_z_mm(cfg, tf),
            "a": carrier.a_centre_mm - ox * p / m,
            "b": carrier.b_window_mm + k * carrier.field_pitch_mm - oy * p / m}


def white_axes(carrier: Carrier) -> dict[str, float]:
    """Stage Z, A, B with the clear window centred in the white target's plane (the white frames)."""
    return {"z": carrier.z_white_mm, "a": carrier.a_centre_mm, "b": carrier.b_window_mm}


@dataclass(frozen=True)
class CarrierView:
    """What the camera sees with the mask at given stage readings and the main lens at f/N."""

    kind: str  # "white" (the window), "pinholes" (a lattice field) or "opaque" (off the fields: no light)
    cfg: CameraConfig  # the camera imaging it: iris and (pinholes) object distance
    scene: Scene | None  # None when opaque
    field: int  # 0 window, k lattice, else off the mask's fields
    frame: ThroughFocus | None = None  # pinholes: u from the actual Z, the nearest lattice offset
    residual_mm: tuple[float, float] = (0.0, 0.0)  # the mask's object-side shift off that lattice offset
    flux_scale: float = 1.0  # multiply the render by this (see `white_flux_scale`)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "field": self.field, "flux_scale": self.flux_scale,
                "through_focus": None if self.frame is None else self.frame.to_dict(),
                "residual_um": [round(1e3 * v, 4) for v in self.residual_mm]}


def iris_config(cfg: CameraConfig, f_number: float) -> CameraConfig:
    """`cfg` itself at (or below) its own f-number efl / D, else stopped to f/N with its distances frozen."""
    if not (math.isfinite(f_number) and f_number >= 1.0):
        raise InputError(f"f-number must be at least 1, not {f_number!r}")
    if f_number <= native_f_number(cfg) + 1e-3:  # an iris cannot open beyond the lens' own rim
        return cfg
    return stopped(cfg, f_number)


def white_flux_scale(cfg: CameraConfig, f_number: float) -> float:
    """What an iris at f/N passes of the white image the renderer makes: (D_N / D)^2. The renderer
    normalizes a white image to the config's `exposure_photons` whatever the aperture (its ray weights
    do not shrink with the rim), so a stopped-down white render must be scaled by the aperture area."""
    return (iris_config(cfg, f_number).main_lens.diameter_mm / cfg.main_lens.diameter_mm) ** 2


def native_f_number(cfg: CameraConfig) -> float:
    """The main lens' full-aperture f-number, efl / D."""
    return cfg.layout.main.efl / cfg.main_lens.diameter_mm


def carrier_view(cfg: CameraConfig, carrier: Carrier, axes: dict[str, float], f_number: float,
                 photons_per_pinhole: float | None = None) -> CarrierView:
    """The view at stage readings `axes` (z, a, b in mm): a physical forward model. The pinholes stay where
    the mask holds them: the lattice field's design points (the images on lens centres at its own u and
    the nearest lattice offset), moved by the mask's residual lateral shift, imaged from the object
    distance the actual Z gives. At the nominal axes of a frame this is exactly `frame_config` and
    `scene`. `photons_per_pinhole` None: the field's protocol exposure (`pinhole_photons` of its design
    |u| at this f-number and the mask's spacing; the light does not follow Z). The white window ignores
    Z: a uniform Lambertian plane that fills the field gives the same image at any distance."""
    z, a, b = (float(axes[k]) for k in ("z", "a", "b"))
    k = round((b - carrier.b_window_mm) / carrier.field_pitch_mm)
    cam = iris_config(cfg, f_number)
    if k == 0:
        return CarrierView("white", cam, WhiteScene(), 0, flux_scale=white_flux_scale(cfg, f_number))
    if not 1 <= k <= len(carrier.focus_offsets_mm):
        return CarrierView("opaque", cam, None, k)
    s = carrier.spacing_lenses
    design = ThroughFocus(carrier.focus_offsets_mm[k - 1], f_number, s, (0, 0), photons_per_pinhole)
    if photons_per_pinhole is None:
        design = replace(design, photons_per_pinhole=pinhole_photons(cfg, design))
    m = magnification(frame_config(cfg, design))
    p = cfg.mla.pitch_um * 1e-3
    dx, dy = a - carrier.a_centre_mm, b - (carrier.b_window_mm + k * carrier.field_pitch_mm)
    if cfg.mla.packing == "hex":  # the nearest lattice offset: the hex cell the shift falls in, as axial (q, r)
        row, col, _, _ = hex_cell(-dx * m / p, -dy * m / p)
        ky = int(row)
        kx = int(col) - ky // 2
    else:
        kx, ky = round(-dx * m / p), round(-dy * m / p)
    sx, sy = axial_shift_lenses(cfg.mla.packing, (kx, ky))
    residual = (dx + sx * p / m, dy + sy * p / m)
    nominal = replace(design, offset_lenses=(kx % s, ky % s))
    pts = tuple((x + residual[0], y + residual[1]) for x, y in scene(cfg, nominal).points_mm)
    base = frozen(cfg) if cam is cfg else cam
    dz = z - carrier.z_white_mm
    cam = replace(base, geometry=replace(base.geometry, object_distance_mm=frozen(cfg).layout.object_distance_mm + dz))
    try:
        frame = replace(nominal, focus_offset_mm=round(focus_offset_at_stage_z(cfg, dz), 6))
    except InputError:
        frame = None  # the pinholes are (nearly) imaged onto the MLA: not a through-focus frame
    return CarrierView("pinholes", cam, PointScene(points_mm=pts, photons=design.photons_per_pinhole), k, frame,
                       residual)
