"""Through-focus analysis: every microlens' focal-length error, with its sign, from +u / -u pinhole frames
(the protocol: mlaqc.optics.throughfocus), and its optical-centre displacement from the spot positions.

Physics. Lens power P = 1/f', sensor a distance s behind its rear principal plane. A pinhole imaged u'
behind the lens' front principal plane (u' < 0: in front) sends it a wave of vergence 1/u'; leaving the
lens the vergence is V = P + 1/u', and the ray at aperture height h lands h (1 - s V) from the spot's
centre. The geometric spot is the lit aperture (the square cell less the corners where the two
surfaces cross) scaled by c - g (+u frame) or c + g (-u frame), c = 1 - s P the lens' own defocus,
g = s / |u'|. Its second moment (x + y) is 2 I (c -/+ g)^2 + floor, I the aperture's per-axis second
moment, the floor the blur the lens' defocus does not change (diffraction, pixel, crosstalk). Measured in
the same window in both frames the floor cancels in the difference

    D = m2(+) - m2(-) = 2 I [g+^2 - g-^2 - 2 c (g+ + g-)]

which is linear in c: the paraxial gain dD/dc = -4 I (g+ + g-). Spherical aberration adds a |h|^2 h
term to each ray: the microlens' own shifts D alike for all lenses, but it changes with the lens' radius,
so it also steepens the slope (Table 1: D moves 8-10 % more than the paraxial defocus alone, traced: the
"gain"); the main lens' matters when a lenslet spans much of the pinhole's disc (1.45x at u = 3 mm) and
makes g vary over the disc; off the axis its field curvature and astigmatism move the typical lens' D
(Table 1 at u = 5 mm: by the equivalent of 1.4 % of focal length at the array's corner). All three come
from the camera's own optics: `model_curves` traces a pinhole through the config's main lens and an MLA
whose lenses all carry a radius error eps (every 0.5 % out to +-15 %), one lens per shell (lenses at the
same distance from their pinhole), on the axis and at FIELD_POINTS field radii.

Pixel sampling. A spot of about a pixel (Table 1: 1-2 px at u = +-10 mm f/8, 1-2.5 px at +-5 mm f/11)
is undersampled, and that is what limited the sizing (issue #12: at +-5 mm f/11, seeds 2-4, -3 % errors
read 0.76-0.99 of their size, median 0.88). Two things, both measured on frames with a third of the
lenses seeded over -12..+12 %:
- its measured second moment depends on where it falls on the pixels, by up to +-0.25 px^2 (x + y), and
  how much depends on its size (binned, a uniform square 1.0 px wide reads 0.5 px^2 apart over its
  positions, one 1.3 px wide 0.11), so the pattern's amplitude swings with a period of about 4 % in eps,
  and a lens whose error changes its spots' sizes has a pattern of its own (the typical lens' fitted
  pattern, applied to it, added 0.2-0.6 % of scatter to the readings of seeded lenses; healthy 0.1 %);
- its measured centroid locks to the pixel's centre, the more the smaller the spot (the model: 0.08-0.24
  px rms over the positions for the smaller spot of a lens 3-11 % off, <= 0.03 px for the larger spot
  of any lens). A sub-pixel pattern fitted on the spots' own centroids is then not zero-mean over the
  lenses whose spot is smaller than the typical one: it took 0.1-0.3 px^2 off D for -8..-2 % lenses
  (the -3 % bias above; the model's curvature between its old nodes at 0 and +-5 % was worth 2 %).
So the model is the measurement's, not the geometric moment: for every shell, field radius and eps, the
traced rays of both frames' spots are binned into pixels with the spot's centre at P x P sub-pixel
positions, put through the config's image formation (as `apply_formation`: diffraction and crosstalk
on the binned image) and read by the same window and moment code as a frame (ModelCurves.spot_m2). Each
lens is read on its own model: its spots' centres from the larger spot's centroid and the smoothly
fitted offset between its two frames' spots (`true_phases`), its D against the model at its shell,
field radius (orientation mirrored onto the traced one) and those phases, less a constant per shell
group (the typical lens' offset: a defocus common to all lenses, the sensor distance, is not read, as
in the white frame's `measure_lenses`; the MLA's slow trend over the array is kept), less what the
typical lenses still show of a first-harmonic phase pattern; the eps of the lens' own curve that
explains it (the mean under its likelihood within BRACKET_NODES nodes of the phase-averaged reading,
with its sd: where a pixel-sized spot's moment stalls over a few % of eps at its phase, as at +-10 mm,
the reading says so) is turned into Δf/f by the thick-lens power of a lens with both radii scaled by
1 + eps (as `measure_lenses` reports). Measured (bench/throughfocus_accuracy.py, +-5 mm f/11, 4 lenses,
seeds 2-6): +-3/5/10 % radius errors sized within 15 % 120 of 120 (was 109), healthy lenses' sd 0.092-
0.094 % (was 0.114-0.116 %) with each frame scaled to 80 % of full well, 0.104-0.106 % at the protocol's
own exposure (50 %, mlaqc.optics.throughfocus.FILL_FRACTION; still 120 of 120), none flagged; at +-10 mm
f/8, 9 lenses (seeds 2-4, 80 %): 58 of 72 (was 33).
`model="paraxial"` reads on the paraxial D instead (spots that are scaled apertures: no aberrations),
with the sub-pixel pattern fitted on the typical spots (`reference_fit`).

Measurement. Each lens' spot is found in its sub-image window (the white frame's grid): the brightest
3 x 3 sum, then the centroid and second moment in a square window of half-width WINDOW_SIGMAS sigma (at
least MIN_WINDOW_PX) around the centroid, iterated, background (the median of the window's outer ring)
subtracted. Window edges weigh pixels by the share of them inside, so the moments move smoothly with the
spot. Both frames of a lens use one window (the larger), so the floor cancels. Lenses not fully lit in
both frames (nearer the disc's traced rim than RIM_MARGIN_LENSES), saturated, off the sensor or unlit are
left out of that pair; a lens read in several pairs gets their inverse-variance mean.

Hex arrays (mla.packing = "hex"): the pinholes sit on the hex sub-lattice (mlaqc.optics.throughfocus), a
lens' nearest pinhole and its (dx, dy) offset come from the Lattice positions (dx in half pitches, dy in
rows of sqrt(3)/2), its shell is dq^2 + dr^2 + dq dr in axial steps (0, 1, 3, 4, 7, ...), the lit aperture
is the hexagonal cell (or the circle of `aperture = "circle"`), and the model is traced on a hex patch
with its centre lens under the pinhole: per shell the lens at 0-30 degrees from the field direction, and
that lens turned 60 degrees for the field's orientation term. A lens is mapped onto the traced one by the
same mirrors and x / y swap as on a square array; the swap turns a hexagonal cell by 90 degrees, which
keeps its second moment (a regular hexagon's is isotropic) but not its exact pixel pattern: the shipped
protocol (every lens read under its own pinhole) sizes ±5 / ±10 % within 15 % on the small hex camera
(tests/test_hex_throughfocus.py, bench/throughfocus_accuracy.py -c fixtures/hex_small_camera.toml).

Frames: prepare them with `prepare_spots` (black-subtracted and normalized, nothing else): the pipeline's
`prepare` suppresses hot pixels, and a focused spot's peak is one to it.

Uncertainty: the moments' shot and read noise (the sensor's electrons per unit from the config, the read
noise from the frame's unlit pixels), propagated, plus (traced model) what the typical lenses scatter
about their models beyond it; through the lens' own curve; scaled up (never down) by a Birge ratio, the
robust spread of the readings of each |u| over their sigmas, so that what the noise model leaves out (a
render's Monte-Carlo noise) is counted.

Speed: a frame is kept as stored (`SpotFrame`; an uncompressed TIFF mapped from its file), and only
the spots' windows are cut and normalized; cutting, the ring median, the first guess and the moments are
compiled (mlaqc.inspection.throughfocus_kernels), the pairs run on a thread per core, the model is cached
on disk (and shipped for the Table 1 camera's protocols): bench/throughfocus_accuracy.py prints the
times, bench/inspection.py --through-focus the whole white + 32-frame inspection.

Optical centre (Shack-Hartmann): a lens' spot centroid moves by d s P (d its optical-centre shift, s P =
1 - c0 ≈ 1) whatever u is. It is read against the paraxial chief ray (through the lens' centre from the
pinhole's image, against the white sub-image centre), the typical lens at the same (dx, dy) from its
pinhole (the main lens' aberrations) and a smooth field over the frame's pinhole positions (the mask's
placement, the main lens' distortion), averaged over the frames.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection import throughfocus_kernels as kern
from mlaqc.inspection.calibrate import Grid
from mlaqc.inspection.rawio import RawFrame, check_exposure, normalized
from mlaqc.optics.config import CameraConfig, require_thick_main_lens
from mlaqc.optics.formation import aperture_corner_radius_um
from mlaqc.optics.lattice import SQRT3_2, Lattice, hex_edge
from mlaqc.optics.paraxial import thick_lens
from mlaqc.optics.sensor import white_level
from mlaqc.optics.throughfocus import (RIM_MARGIN_LENSES, ThroughFocus, frame_config, inner_radius_lenses,  # noqa: F401
                                      lens_centres_mm, pair_radius_lenses, pinhole_lenses)
from mlaqc.parallel import thread_map

WINDOW_SIGMAS = 4.0  # moment window half-width, in the spot's per-axis rms
MIN_WINDOW_PX = 2.0  # never narrower: a spot smaller than a pixel still has the pixel's own width
MIN_FLUX = 0.25  # a spot with less than this share of the pair's median flux is not read (no lens there)
SATURATED = 0.999  # a prepared (normalized) pixel at or above this is at the white level
RING_PX = 2  # the sub-image window's outer ring this wide gives the background
MIN_SHELL_LENSES = 5  # a shell's reference needs this many lenses (else the |u| group's median)
PHASE_MIN_LENSES = 12  # the phase-pattern fit needs this many lenses per fitted term


@dataclass(frozen=True)
class SpotFrame:
    """A through-focus frame as `measure_through_focus` reads it: the counts as stored and the scale that
    normalizes them, (data - black) / span. A pinhole frame lights a few per cent of the sensor, so only
    the windows the analysis cuts are normalized (the same float32 operations as `rawio.normalized`, so
    the same values), never the whole frame: 32 frames of the shipped protocol are then read at 8 MB
    each as stored instead of 16 MB of float32 written and read again."""

    data: np.ndarray  # (H, W): integer counts, or an already normalized float32 frame (black 0, span 1)
    black: float = 0.0
    span: float = 1.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape  # type: ignore[return-value]

    @classmethod
    def of(cls, img: SpotFrame | np.ndarray) -> SpotFrame:
        """`img` itself, or an array taken as an already normalized frame."""
        return img if isinstance(img, SpotFrame) else cls(np.asarray(img))

    @property
    def counts(self) -> bool:
        """True for integer data: normalized by construction, no NaN (float data may hold anything)."""
        return self.data.dtype.kind in "iu"

    def image(self) -> np.ndarray:
        """The whole frame normalized (float32), as the analysis' windows see it: for display."""
        out = self.data.astype(np.float32)  # a copy, then in place
        out -= np.float32(self.black)
        out /= np.float32(self.span)
        return out


def prepare_spots(frame: RawFrame) -> SpotFrame:
    """A through-focus frame for `measure_through_focus`: black-subtracted and normalized (CFA sites
    balanced), without the hot-pixel pass of `pipeline.prepare` (which takes a focused spot's peak pixel
    for a hot pixel and cuts it). A monochrome integer frame stays as stored (`SpotFrame`); a CFA frame's
    site gains need the whole frame, so it is normalized whole."""
    if frame.cfa is None and frame.data.dtype.kind in "iu":
        return SpotFrame(frame.data, float(frame.black_level), float(frame.white_level - frame.black_level))
    return SpotFrame(normalized(frame).astype(np.float32, copy=False))


# ---------------------------------------------------------------------------------------------- results

# per-lens readings as lenses.csv / report.json name them: column -> (ThroughFocusResult field, unit, meaning)
TF_MEASUREMENTS: dict[str, tuple[str, str, str]] = {
    "tf_focal_rel": ("focal_rel", "1", "focal-length error Δf/f from the through-focus pinhole pairs, vs the typical lens"),
    "tf_focal_sigma_rel": ("focal_sigma_rel", "1", "1-sigma uncertainty of tf_focal_rel"),
    "tf_radius_rel": ("radius_rel", "1", "the same reading as the radius error (both radii scaled) it equals"),
    "tf_centre_dx_um": ("centre_dx_um", "µm", "optical-centre displacement along x from the spot positions (Shack-Hartmann)"),
    "tf_centre_dy_um": ("centre_dy_um", "µm", "optical-centre displacement along y (down) from the spot positions"),
    "tf_centre_sigma_um": ("centre_sigma_um", "µm", "1-sigma uncertainty of each tf centre component"),
}



@dataclass(frozen=True)
class PairReading:
    """One +u / -u pair: what it read and the figures it was read with."""

    focus_offset_mm: float  # |u|
    offset_lenses: tuple[int, int]
    lenses: int  # lenses read in this pair
    g_plus: float  # s / |u'| of the +u frame
    g_minus: float
    gain: float  # the traced model's dD/dc over the paraxial -4 I (g+ + g-), at the design lens
    birge: float  # the sigma scale (>= 1) of this |u|'s readings
    window_px: float  # median moment window half-width
    saturated: int  # lenses left out because a pixel of their spot was saturated


@dataclass(frozen=True)
class ThroughFocusResult:
    """Per-lens (rows, cols) arrays; NaN (or False) where a lens was not read."""

    focal_rel: np.ndarray  # Δf/f against the array's typical lens
    focal_sigma_rel: np.ndarray  # its 1-sigma
    radius_rel: np.ndarray  # the reading as the radius error (both radii scaled by 1 + eps) it equals
    covered: np.ndarray  # bool: read in at least one pair
    delta_px2: np.ndarray  # D - D(typical lens of its shell), px^2, phase pattern removed (mean over pairs)
    centre_dx_um: np.ndarray  # optical-centre displacement, x right, MLA plane, vs the typical lens
    centre_dy_um: np.ndarray  # y down
    centre_sigma_um: np.ndarray  # 1-sigma of each component
    pairs: tuple[PairReading, ...]
    focal_length_um: float  # the design microlens' effective focal length
    timings_s: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Array-wide figures: coverage, median focal error and sigma, and each pair's figures."""
        ok = self.covered & np.isfinite(self.focal_rel)

        def num(x) -> float | None:
            return float(x) if x is not None and np.isfinite(x) else None

        return {"lenses_covered": int(ok.sum()), "coverage": float(ok.mean()),
                "focal_rel_median": num(np.median(self.focal_rel[ok])) if ok.any() else None,
                "focal_sigma_rel_median": num(np.median(self.focal_sigma_rel[ok])) if ok.any() else None,
                "centre_sigma_um_median": (num(np.nanmedian(self.centre_sigma_um))
                                           if np.isfinite(self.centre_sigma_um).any() else None),
                "focal_length_um": self.focal_length_um,
                "pairs": [{"u_mm": p.focus_offset_mm, "offset": list(p.offset_lenses), "lenses": p.lenses,
                           "gain": p.gain, "birge": p.birge, "window_px": p.window_px,
                           "saturated": p.saturated} for p in self.pairs]}


# ---------------------------------------------------------------------------------------------- optics


@dataclass(frozen=True)
class Optics:
    """What the analysis needs of the camera: distances in mm, the aperture's moment in px^2."""

    s_mm: float  # rear principal plane to sensor
    front_to_mid_mm: float  # front principal plane to the MLA mid-plane (u is measured from the mid-plane)
    pupil_mm: float  # main lens' rear principal plane to the MLA mid-plane (white sub-image centres)
    pixel_mm: float
    aperture_i_px2: float  # per-axis second moment of the lit aperture, in sensor px^2 (unscaled)
    c0: float  # 1 - s P of the design lens
    e_per_unit: float  # electrons per normalized unit (white - black level) of a prepared frame

    def u_prime(self, u_mm: float) -> float:
        return u_mm + self.front_to_mid_mm

    def g(self, u_mm: float) -> float:
        return self.s_mm / abs(self.u_prime(u_mm))


@functools.lru_cache(maxsize=8)
def optics(cfg: CameraConfig) -> Optics:
    """The first-order facts of `cfg` the reading uses."""
    lay, mla, s = cfg.layout, cfg.mla, cfg.sensor
    micro = lay.micro
    s_mm = lay.sensor_gap_mm + micro.rear_principal  # H' lies rear_principal before the rear vertex
    pixel_mm = cfg.pixel_at_mla_um * 1e-3
    span = white_level(s) - s.black_level_dn
    return Optics(s_mm=s_mm, front_to_mid_mm=0.5 * mla.thickness_um * 1e-3 - micro.front_principal,
                  pupil_mm=lay.pupil_to_mla_mm, pixel_mm=pixel_mm,
                  aperture_i_px2=aperture_moment_mm2(cfg) / pixel_mm ** 2, c0=1.0 - s_mm / micro.efl,
                  e_per_unit=span / s.gain_dn_per_e)


def aperture_moment_mm2(cfg: CameraConfig, samples: int = 801) -> float:
    """Per-axis second moment (mm^2, about its centre) of one lens' lit aperture: its cell (less the black
    matrix) or its circular aperture, where both surfaces exist (inside the radius where they cross). With
    'clear' corners or gaps the light through them passes unfocused and lands outside the spot, so the spot
    is made by the same aperture."""
    mla = cfg.mla
    r_um = aperture_corner_radius_um(replace(cfg, mla=replace(mla, corners="opaque")))
    if mla.packing == "hex":
        half = mla.pitch_um / math.sqrt(3.0)  # the hexagon's corner (its flats are half a pitch out)
    elif mla.aperture == "circle":
        half = 0.5 * mla.pitch_um
    else:
        half = 0.5 * (mla.pitch_um - mla.black_matrix_um)  # the square box is the cell
    x = (np.arange(samples) + 0.5) / samples * 2 * half - half
    xx, yy = np.meshgrid(x, x)
    inside = xx * xx + yy * yy <= r_um * r_um
    if mla.aperture == "circle":
        inside &= np.hypot(xx, yy) <= 0.5 * mla.aperture_diameter_um
    elif mla.packing == "hex":
        inside &= hex_edge(xx / mla.pitch_um, yy / mla.pitch_um) >= 0.5 * mla.black_matrix_um / mla.pitch_um
    return float(np.sum(xx[inside] ** 2) / inside.sum()) * 1e-6


def focal_rel_of_radius(cfg: CameraConfig, radius_rel) -> np.ndarray:
    """Δf/f of the microlens with both radii scaled by 1 + radius_rel, thickness kept (thick-lens power)."""
    m = cfg.mla
    k = 1.0 + np.asarray(radius_rel, dtype=np.float64)
    f = thick_lens(m.radius_front_um * k, m.radius_back_um * k, m.thickness_um, m.refractive_index).efl
    return f / thick_lens(m.radius_front_um, m.radius_back_um, m.thickness_um, m.refractive_index).efl - 1.0


# --------------------------------------------------------------------------------------- model curves


@dataclass(frozen=True)
class ModelCurves:
    """What the camera's optics make of one lens' pair of spots, per shell (squared distance from its
    pinhole, in lenses), traced at the radius errors `eps`:

    - `curves`: the geometric D(eps) - D(0) on the axis (exact second moments of the traced rays, px^2),
      which gives the `gain` over the paraxial slope;
    - `field_a`, `field_b`: how the geometric D(0) changes over the field: at field radius r,
      D(0; r) - D(0; 0) = a(r) + b(r) cos 2 phi, phi the angle between the lens' offset from its pinhole
      and the field direction (the main lens' field curvature and astigmatism);
    - `spot_m2` (traced models only): the second moment the analysis *measures* of each frame's spot of
      the shell's traced lens (`offsets`: (a, b) lenses from the pinhole along and across the field),
      at each field radius and radius error, with the spot's centre at each of P x P sub-pixel positions:
      the traced rays binned into pixels, put through the config's image formation (diffraction,
      crosstalk, as `apply_formation`) and read by `_spot_window` and `moments` in the pair's common
      window, exactly as a frame's spots are. A spot of a pixel or two is undersampled: what its moment
      reads depends on where it falls on the pixels, by up to +-0.25 px^2, by how much swinging with the
      spot's size (a period of about 4 % in eps), and the phase-averaged reading is not the geometric one
      (the window cuts the formation's tails differently for each size). Reading each lens on its own
      spots' model removes both."""

    eps: np.ndarray
    shells: np.ndarray  # (S,) int
    curves: np.ndarray  # (S, E) px^2
    gain: float  # the centre shell's slope at eps = 0 over the paraxial one
    field_mm: np.ndarray = field(default_factory=lambda: np.zeros(1))  # (R,) field radii, from 0
    field_a: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))  # (S, R) px^2
    field_b: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))  # (S, R) px^2
    # (S, 2) traced lens (a, b), a >= b >= 0 (hex: float (x, y) pitches, 0 <= phi <= 30 degrees)
    offsets: np.ndarray = field(default_factory=lambda: np.zeros((1, 2), np.int64))
    spot_m2: np.ndarray | None = None  # (S, R, 2, E, P, P) px^2: [.., frame (+u, -u), eps, y phase, x phase]
    key: str = ""  # `model_key` of a traced model

    def field_offset(self, shell: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray) -> np.ndarray:
        """D(0) of each lens' disc position and orientation minus its shell's on-axis D(0), px^2."""
        k = self.shell_index(shell)
        r = np.hypot(pin_mm[:, 0], pin_mm[:, 1])
        f2 = self.field_mm ** 2
        a = _interp_rows(r * r, f2, self.field_a, k)
        b = _interp_rows(r * r, f2, self.field_b, k)
        return a + b * _cos2(dxy, pin_mm)

    def shell_index(self, shell: np.ndarray) -> np.ndarray:
        """Index into `shells` of each lens' shell (the nearest one the model has)."""
        s = np.asarray(shell)
        j = np.clip(np.searchsorted(self.shells, s), 1, max(len(self.shells) - 1, 1))
        if len(self.shells) == 1:
            return np.zeros(s.shape, np.int64)
        lo = self.shells[j - 1]
        return np.where(np.abs(s - lo) <= np.abs(self.shells[j] - s), j - 1, j)


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, k: np.ndarray) -> np.ndarray:
    """np.interp(x[i], xp, fp[k[i]]) for every i (rows of fp picked per point; held beyond the ends)."""
    if len(xp) == 1:
        return fp[k, 0]
    j = np.clip(np.searchsorted(xp, x) - 1, 0, len(xp) - 2)
    t = np.clip((x - xp[j]) / (xp[j + 1] - xp[j]), 0.0, 1.0)
    return fp[k, j] * (1.0 - t) + fp[k, j + 1] * t


def _cos2(dxy: np.ndarray, pin_mm: np.ndarray) -> np.ndarray:
    """cos 2 phi, phi the angle between each lens' offset from its pinhole and the field direction."""
    r2 = pin_mm[:, 0] ** 2 + pin_mm[:, 1] ** 2
    d2 = (dxy[:, 0] ** 2 + dxy[:, 1] ** 2).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        along = (dxy[:, 0] * pin_mm[:, 0] + dxy[:, 1] * pin_mm[:, 1]) ** 2
        return np.where((d2 > 0) & (r2 > 0), 2.0 * along / (d2 * r2) - 1.0, 0.0)


MODEL_EPS_STEP = 0.005  # the model is traced at radius errors this far apart ...
MODEL_EPS_MAX = 0.15  # ... out to +-15 % (beyond, the end segments extend)
MODEL_EPS = tuple(float(v) for v in np.round(np.arange(-MODEL_EPS_MAX, MODEL_EPS_MAX + 1e-9, MODEL_EPS_STEP), 6))
MODEL_RAYS = 500_000  # pupil rays per frame of the model (a low-discrepancy set; only those reaching a shell's lens are traced on)
MODEL_PHASES = 8  # sub-pixel spot positions per axis at which the model's spots are read
MODEL_FINE = 16  # ray bins per pixel side before the model's spots are pixelated (a multiple of MODEL_PHASES)
SPOT_REACH_MM = 0.03  # a model spot's rays are those within this of its centroid (|1 - sV| <= 0.5)
FIELD_POINTS = 3  # field radii the model is traced at, 0 to the array's corner, even in r^2 (its D is linear in r^2)
MODEL_FORMAT = 2  # the model's definition and its cache file's layout


def model_curves(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float, *, rebuild: bool = False) -> ModelCurves:
    """The camera's model of one lens' pair of spots, shell by shell out to `r_in` lenses (see
    ModelCurves): from the package, else the disk cache (keyed by the optics, the image formation, the
    pixel and the pair geometry: `model_key`; `mlaqc.models.store`), else traced now and cached (Table 1:
    6 s at +-5 mm f/11, its one shell; 8 s at +-10 mm f/8, five shells, on one core); `rebuild` traces it
    again whatever is stored."""
    require_thick_main_lens(cfg, "the through-focus measurement (pinhole frames)")
    return _model_curves(cfg, abs(float(u_mm)), float(f_number), round(max(float(r_in), 0.0), 4), rebuild)


def model_key(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float) -> str:
    """Content hash of everything that shapes `model_curves`: the main lens, the MLA's design (and its
    lens count: the field's extent), the distances, the pixel, the formation's blur, Fresnel, the pair
    geometry and the model's own settings."""
    import hashlib
    import json

    from mlaqc.models.reference import geometry_hash_view, mla_hash_view
    from mlaqc.optics.formation import blur_key

    d = cfg.to_dict()
    keep = {"main_lens": d["main_lens"], "mla": mla_hash_view(d["mla"], design=True), "geometry": geometry_hash_view(d["geometry"]),
            "pixel_um": cfg.pixel_at_mla_um, "fresnel": d["trace"]["fresnel"],
            **blur_key(cfg),
            "protocol": [abs(float(u_mm)), float(f_number), round(max(float(r_in), 0.0), 4)],
            "model": [MODEL_FORMAT, list(MODEL_EPS), MODEL_RAYS, MODEL_PHASES, MODEL_FINE, SPOT_REACH_MM, FIELD_POINTS,
                      WINDOW_SIGMAS, MIN_WINDOW_PX, RING_PX, int(math.floor(cfg.layout.subimage_pitch_px / 2))]}
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


_MODEL_ARRAYS = ("eps", "shells", "curves", "field_mm", "field_a", "field_b", "offsets", "spot_m2")


@functools.lru_cache(maxsize=16)
def _model_curves(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float, rebuild: bool = False) -> ModelCurves:
    from mlaqc.models.store import stored

    key = model_key(cfg, u_mm, f_number, r_in)
    return stored(f"throughfocus_{key}.npz", lambda: _as_stored(trace_model(cfg, u_mm, f_number, r_in)),
                  lambda path: load_model(path, key), save_model, rebuild=rebuild)


def _as_stored(curves: ModelCurves) -> ModelCurves:
    """The model as its file keeps it (spot_m2 in float32), so that a traced and a read model read alike."""
    return replace(curves, spot_m2=curves.spot_m2.astype(np.float32).astype(np.float64))


def save_model(curves: ModelCurves, path) -> None:
    """Write `curves` (a traced model) as compressed NPZ, atomically, under its `model_key` (`key`)."""
    import io

    from mlaqc.atomic import write_bytes_atomic

    buf = io.BytesIO()
    np.savez_compressed(buf, key=curves.key, gain=curves.gain,
                        **{k: (getattr(curves, k).astype(np.float32) if k == "spot_m2" else getattr(curves, k))
                           for k in _MODEL_ARRAYS})
    write_bytes_atomic(path, buf.getvalue())


def load_model(path, key: str) -> ModelCurves:
    """Read a model written by `save_model`; ValueError if it is not the model of `key`."""
    with np.load(path, allow_pickle=False) as z:
        if str(z["key"]) != key:
            raise ValueError(f"{path} holds the through-focus model {z['key']}, not {key}")
        arrays = {k: z[k] for k in _MODEL_ARRAYS}
        gain = float(z["gain"])
    arrays["spot_m2"] = arrays["spot_m2"].astype(np.float64)
    return ModelCurves(gain=gain, key=key, **arrays)


class _Landing:
    """The rays of one pinhole (`field_mm` along x from the axis, under the patch's centre lens; `pupil`:
    (2, N) uniform draws on the pupil) that reach lenses `targets` of the patch MLA, traced through the
    main lens once; `land(eps)` traces them on
    through an MLA whose lenses all carry the radius error eps, to the sensor."""

    def __init__(self, patch: CameraConfig, tf: ThroughFocus, field_mm: float, targets: np.ndarray, pupil: np.ndarray):
        from mlaqc.optics.errormap import ErrorMap
        from mlaqc.optics.raytrace import Camera
        from mlaqc.optics.render import source_region
        from mlaqc.optics.scene import sample_points
        from mlaqc.optics.throughfocus import magnification

        targets = np.unique(targets)  # numbered in this order
        self.n = patch.mla.count_w
        if patch.mla.packing == "hex":  # the centre lens, not the patch's bounding box, under the pinhole
            rows, cols = patch.mla.count_h, patch.mla.count_w
            xc = float(Lattice.of(patch).position(rows // 2, cols // 2)[0])
            self.zero = ErrorMap.zeros(rows, cols, "hex").with_globals(mla_shift_x_um=1e3 * (field_mm - xc))
        else:
            self.zero = ErrorMap.zeros(self.n, self.n).with_globals(mla_shift_x_um=1e3 * field_mm)
        self.fc = frame_config(patch, tf)
        self.cam = Camera(self.fc, self.zero)
        x_obj = -field_mm / magnification(self.fc)  # the main lens inverts
        r = sample_points(source_region(self.cam), pupil, x_obj, 0.0, square=True)
        self.cam.main.trace(r)
        self.cam.to_mla(r)
        zf = self.cam.mla.z_front
        with np.errstate(invalid="ignore", divide="ignore"):
            cell, on = self.cam.mla.cell_of(r.x + (zf - r.z) * r.L / r.N, r.y + (zf - r.z) * r.M / r.N)
        keep = np.flatnonzero(on & (r.w > 0) & np.isin(cell, targets))
        lens = np.searchsorted(targets, cell[keep])
        order = np.argsort(lens, kind="stable")  # each target's rays together: sums by cumulative sums
        self.lens = lens[order]
        self.base = [a[keep[order]] for a in (r.x, r.y, r.z, r.L, r.M, r.N, r.w)]
        self.count = len(targets)
        self.bounds = np.searchsorted(self.lens, np.arange(self.count + 1))

    def land(self, e: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sensor x, y (mm, camera frame) and weight of every ray (weight 0: lost, or beyond SPOT_REACH_MM
        of its lens' spot: a ray the vertex-plane cell gave to the wrong lens lands a pitch away)."""
        from mlaqc.optics.errormap import ErrorMap
        from mlaqc.optics.raytrace import MicrolensArray, Rays

        shape = self.zero.shape
        em = ErrorMap(shape, {**self.zero.lens, "radius_front_rel": np.full(shape, e),
                              "radius_back_rel": np.full(shape, e)}, self.zero.globals, self.zero.packing)
        rr = Rays(*(a.copy() for a in self.base))
        MicrolensArray(self.fc, em).trace(rr)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (self.cam.z_sensor - self.cam.z_mla - rr.z) / rr.N
        w = np.where(np.isfinite(rr.w) & np.isfinite(t), rr.w, 0.0)
        x, y = np.where(w > 0, rr.x + t * rr.L, 0.0), np.where(w > 0, rr.y + t * rr.M, 0.0)
        for _ in range(2):
            mx, my = self.centroid(x, y, w)
            w = np.where((np.abs(x - mx[self.lens]) < SPOT_REACH_MM) & (np.abs(y - my[self.lens]) < SPOT_REACH_MM), w, 0.0)
        return x, y, w

    def sums(self, v: np.ndarray) -> np.ndarray:
        """Per target, the sum of v over its rays."""
        out = np.zeros(self.count)
        start = self.bounds[:-1]
        some = self.bounds[1:] > start  # (reduceat would give an empty run the next ray's value)
        if some.any():
            out[some] = np.add.reduceat(v, start[some])
        return out

    def centroid(self, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(invalid="ignore", divide="ignore"):
            sw = self.sums(w)
            return self.sums(w * x) / sw, self.sums(w * y) / sw

    def moment(self, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Geometric second moment x + y (mm^2) of each target's spot."""
        mx, my = self.centroid(x, y, w)
        dx, dy = x - mx[self.lens], y - my[self.lens]
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.sums(w * (dx * dx + dy * dy)) / self.sums(w)


def _pixelated(land: _Landing, x: np.ndarray, y: np.ndarray, w: np.ndarray, pick: np.ndarray, pixel_mm: float,
               half: int, psf: np.ndarray) -> np.ndarray:
    """(T, P, P, n, n) the spots of `land`'s targets `pick` as a frame holds them, each centred on the
    window's centre pixel shifted by (i, j) / P px (y, x): rays binned into pixels, then the formation's
    PSF (`apply_formation`'s order), n = 2 half + 1. Each spot sums to 1."""
    from scipy.signal import fftconvolve

    P, Q = MODEL_PHASES, MODEL_FINE
    step = Q // P
    hs = int(math.ceil(SPOT_REACH_MM / pixel_mm)) + 1  # the spot's own half-width, whatever its phase
    ns = 2 * hs + 1
    pad = (P - 1) * step
    F = ns * Q + pad
    T = len(pick)
    slot = np.full(land.count, -1)
    slot[pick] = np.arange(T)
    mx, my = (np.nan_to_num(v) for v in land.centroid(x, y, w))  # a lens no ray reaches: no spot
    t = slot[land.lens]
    fx = np.floor(((x - mx[land.lens]) / pixel_mm + hs + 0.5) * Q).astype(np.int64) + pad
    fy = np.floor(((y - my[land.lens]) / pixel_mm + hs + 0.5) * Q).astype(np.int64) + pad
    ok = (t >= 0) & (w > 0) & (fx >= pad) & (fx < F) & (fy >= pad) & (fy < F)
    fine = np.bincount((t[ok] * F + fy[ok]) * F + fx[ok], w[ok], T * F * F).reshape(T, F, F)
    with np.errstate(invalid="ignore", divide="ignore"):
        fine /= fine.sum(axis=(1, 2), keepdims=True)
    integ = np.zeros((T, F + 1, F + 1))
    integ[:, 1:, 1:] = np.cumsum(np.cumsum(fine, axis=1), axis=2)
    bound = np.arange(ns + 1)[None, :] * Q - np.arange(P)[:, None] * step + pad  # (P, ns + 1): phase i shifts by +i/P px
    cut = integ[:, bound[:, :, None, None], bound[None, None, :, :]]  # (T, P, ns + 1, P, ns + 1)
    pix = np.diff(np.diff(cut, axis=2), axis=4).transpose(0, 1, 3, 2, 4)  # (T, P, P, ns, ns)
    if psf.shape != (1, 1):
        pix = np.maximum(fftconvolve(pix, psf[None, None, None], mode="full", axes=(3, 4)), 0.0)
    c = pix.shape[-1] // 2  # the spot's centre pixel
    n = 2 * half + 1
    out = np.zeros((T, P, P, n, n))
    a = min(c, half)
    out[..., half - a:half + a + 1, half - a:half + a + 1] = pix[..., c - a:c + a + 1, c - a:c + a + 1]
    return out


def _read_model_spots(plus: np.ndarray, minus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the analysis measures of model spot images (..., n, n) of the +u and -u frames of one lens at
    the same sub-pixel position: each frame's window (`_spot_window`), the pair's common one, `moments`."""
    shape = plus.shape[:-2]
    out = []
    sps = []
    for img in (plus, minus):
        cells = img.reshape(-1, *img.shape[-2:])
        zeros = np.zeros(len(cells))
        sp = Spots(cells, zeros.astype(np.int64), zeros.astype(np.int64), zeros, 0.0, zeros.astype(bool))
        sps.append((sp, *_spot_window(sp, 1.0)))
    w = np.maximum(sps[0][3], sps[1][3])
    for sp, cx, cy, _ in sps:
        out.append(moments(sp, cx, cy, w, 1.0, variance=False)[2].reshape(shape))
    return out[0], out[1]


def trace_model(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float) -> ModelCurves:
    """Trace `model_curves` (no cache)."""
    from mlaqc.models.signatures import patch_config
    from mlaqc.optics.formation import formation_kernels

    reach = int(math.floor(r_in))
    n = 2 * reach + 3
    patch = patch_config(cfg, n)  # the pinhole's image on the centre lens
    opt = optics(cfg)
    half = int(math.floor(cfg.layout.subimage_pitch_px / 2))
    psf = formation_kernels(cfg, (1, 1), with_prnu=False).psf
    if cfg.mla.packing == "hex":
        shells, along, across, offsets, cos_along, cos_across = _hex_model_lenses(patch, r_in)
        S = len(shells)
    else:
        # one lens per shell, (a, b) with a >= b >= 0 (a along x), and its mirror (b, a) for the field's
        # orientation term
        uniq = {}
        for a in range(reach + 1):
            for b in range(a + 1):
                if a * a + b * b <= r_in * r_in:
                    uniq.setdefault(a * a + b * b, (a, b))
        shells = np.array(sorted(uniq))
        S = len(shells)
        c = n // 2
        along = np.array([(c + uniq[s][1]) * n + (c + uniq[s][0]) for s in shells])  # row c + b, col c + a
        across = np.array([(c + uniq[s][0]) * n + (c + uniq[s][1]) for s in shells])
    eps = np.array(MODEL_EPS)
    zero = int(np.argmin(np.abs(eps)))
    tf = ThroughFocus(focus_offset_mm=u_mm, f_number=f_number)
    frames = (replace(tf, focus_offset_mm=u_mm), replace(tf, focus_offset_mm=-u_mm))
    p = cfg.mla.pitch_um * 1e-3
    if cfg.mla.packing == "hex":
        corner = 0.5 * p * math.hypot(*Lattice.of(cfg).span_uv)
    else:
        corner = 0.5 * p * math.hypot(cfg.mla.count_w - 1, cfg.mla.count_h - 1)
    radii = corner * np.sqrt(np.linspace(0.0, 1.0, FIELD_POINTS))
    targets = np.concatenate([along, across])
    P = MODEL_PHASES
    spot = np.zeros((S, len(radii), 2, len(eps), P, P))
    geo = np.zeros((len(radii), 2, len(eps), 2 * S))  # geometric x + y, mm^2
    slots = np.searchsorted(np.unique(targets), targets)  # _Landing numbers its targets sorted
    from mlaqc.optics import lowdisc

    pupil = lowdisc.batch_uniforms(0x7F0C, MODEL_RAYS, 2)
    for i, rf in enumerate(radii):
        lands = [_Landing(patch, f, rf, targets, pupil) for f in frames]
        for j, e in enumerate(eps):
            imgs = []
            for k, land in enumerate(lands):
                x, y, w = land.land(e)
                geo[i, k, j] = land.moment(x, y, w)[slots]
                imgs.append(_pixelated(land, x, y, w, slots[:S], opt.pixel_mm, half, psf))
            m2p, m2m = _read_model_spots(imgs[0], imgs[1])
            spot[:, i, 0, j], spot[:, i, 1, j] = m2p, m2m
    d = (geo[:, 0] - geo[:, 1]) / opt.pixel_mm ** 2  # (R, E, 2S)
    curves = d[0, :, :S].T - d[0, zero, :S][:, None]  # (S, E) on the axis
    slope = (curves[0, zero + 1] - curves[0, zero - 1]) / (eps[zero + 1] - eps[zero - 1])
    dc = (focal_rel_of_radius(cfg, eps[zero + 1]) - focal_rel_of_radius(cfg, eps[zero - 1])) \
        / (eps[zero + 1] - eps[zero - 1]) * (1.0 - opt.c0)  # dc/deps of c = 1 - s P at the design lens
    paraxial = -4.0 * opt.aperture_i_px2 * (opt.g(u_mm) + opt.g(-u_mm)) * dc
    d0 = d[:, zero] - d[:1, zero]  # (R, 2S): D(0) over the field, from the axis'
    d_along, d_across = d0[:, :S].T, d0[:, S:].T  # (S, R)
    if cfg.mla.packing == "hex":  # D(0) = a + b cos 2 phi at the two lenses' cos 2 phi
        dc2 = (cos_along - cos_across)[:, None]
        field_b = np.where(shells[:, None] > 0, (d_along - d_across) / np.where(dc2 == 0, 1.0, dc2), 0.0)
        field_a = d_along - field_b * cos_along[:, None]
    else:
        cos2 = np.array([(uniq[s][0] ** 2 - uniq[s][1] ** 2) / s if s else 0.0 for s in shells])
        field_b = np.where(np.abs(cos2)[:, None] > 1e-9, (d_along - d_across) / (2.0 * np.where(cos2 == 0, 1.0, cos2))[:, None], 0.0)
        field_a = 0.5 * (d_along + d_across)
        offsets = np.array([uniq[s] for s in shells], np.int64)
    return ModelCurves(eps, shells, curves, float(slope / paraxial), radii, field_a, field_b, offsets, spot,
                       model_key(cfg, u_mm, f_number, r_in))


def _hex_model_lenses(patch: CameraConfig, r_in: float):
    """The hex model's traced lenses: per shell (dq^2 + dr^2 + dq dr <= r_in^2, axial steps from the patch's
    centre lens) the one at 0 <= phi <= 30 degrees from +x (every hex offset maps onto it by the lattice's
    symmetry) and the same lens turned 60 degrees (a lattice point at another cos 2 phi, for the field's
    orientation term). Returns shells, their flat patch indices (along, turned), offsets (x, y pitches,
    float) and both lenses' cos 2 phi."""
    rows, cols = patch.mla.count_h, patch.mla.count_w
    r0, q0 = rows // 2, cols // 2 - (rows // 2) // 2
    k = int(math.floor(r_in)) + 1
    pick: dict[int, tuple[int, int]] = {}
    for dr in range(k + 1):
        for dq in range(-k, k + 1):
            x, y = dq + 0.5 * dr, SQRT3_2 * dr
            sh = dq * dq + dr * dr + dq * dr
            if sh <= r_in * r_in + 1e-9 and x >= 0 and y <= x / math.sqrt(3.0) + 1e-9:
                pick.setdefault(sh, (dq, dr))
    shells = np.array(sorted(pick), np.int64)

    def flat(dq: int, dr: int) -> int:
        r = r0 + dr
        return r * cols + (q0 + dq) + r // 2

    def cos2(dq: int, dr: int) -> float:
        x, y = dq + 0.5 * dr, SQRT3_2 * dr
        return (x * x - y * y) / (x * x + y * y) if dq or dr else 0.0

    steps = [pick[s] for s in shells]
    turned = [(-dr, dq + dr) for dq, dr in steps]  # 60 degrees round: a1 -> a2, a2 -> a2 - a1
    return (shells, np.array([flat(*v) for v in steps]), np.array([flat(*v) for v in turned]),
            np.array([(dq + 0.5 * dr, SQRT3_2 * dr) for dq, dr in steps], np.float64),
            np.array([cos2(*v) for v in steps]), np.array([cos2(*v) for v in turned]))


def paraxial_curves(cfg: CameraConfig, u_mm: float, shells: np.ndarray) -> ModelCurves:
    """The paraxial D(eps) - D(0) (a scaled-aperture spot, no aberrations), the same for every shell."""
    opt = optics(cfg)
    eps = np.array(MODEL_EPS)
    c = 1.0 - (1.0 - opt.c0) / (1.0 + focal_rel_of_radius(cfg, eps))
    gp, gm = opt.g(u_mm), opt.g(-u_mm)
    d = 2.0 * opt.aperture_i_px2 * ((c - gp) ** 2 - (c + gm) ** 2)
    d = d - d[np.argmin(np.abs(eps))]
    flat = np.zeros((len(shells), 1))
    return ModelCurves(eps, np.asarray(shells), np.tile(d, (len(shells), 1)), 1.0, np.zeros(1), flat, flat)


def _invert(curves: ModelCurves, shell: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """eps with curve_shell(eps) = x (piecewise linear, extended linearly past the ends) and the curve's
    slope there; a shell the model lacks takes the nearest one."""
    return _invert_rows(curves.curves[curves.shell_index(shell)], curves.eps, x)


def _invert_rows(cv: np.ndarray, e: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of cv (L, E), decreasing in e: the e where it crosses x (piecewise linear, the end
    segments extended) and its slope there."""
    seg = np.sum(cv[:, 1:-1] >= x[:, None], axis=1)  # 0 .. E-2
    lo = np.take_along_axis(cv, seg[:, None], 1)[:, 0]
    hi = np.take_along_axis(cv, seg[:, None] + 1, 1)[:, 0]
    slope = (hi - lo) / (e[seg + 1] - e[seg])
    with np.errstate(invalid="ignore", divide="ignore"):
        out = e[seg] + (x - lo) / slope
    return out, slope


def true_phases(pos: np.ndarray, m2: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(L, 4) sub-pixel positions in [0, 1) of the centres of each lens' +u and -u spots (x, y each).

    A spot of a pixel or less is centroided towards its pixel's centre (the sampled centroid locks to
    the pixels), the more the smaller it is, so each frame's own centroid would give the small spots a
    phase pattern of their own. The larger of the lens' two spots is centroided within a few hundredths
    of a pixel (ModelCurves' spots); the other frame's spot sits where the offset between the frames'
    spots puts it: the median of the lenses at the same (dx, dy) from their pinhole plus a smooth
    field and a constant per pair (`_field_removed`), fitted over all lenses, so locking averages out."""
    delta = pos[:, :2] - pos[:, 2:]
    cls = offset_classes(dxy)
    smooth = np.empty_like(delta)
    for j in range(2):
        rest = _field_removed(_class_centred(delta[:, j], cls), pin_mm, frame)
        smooth[:, j] = np.where(np.isfinite(rest), delta[:, j] - rest, delta[:, j])
    plus_big = (m2[:, 0] >= m2[:, 1])[:, None]
    centre_p = np.where(plus_big, pos[:, :2], pos[:, 2:] + smooth)
    centre_m = np.where(plus_big, pos[:, :2] - smooth, pos[:, 2:])
    c = np.concatenate([centre_p, centre_m], axis=1)
    return c - np.floor(c)


def _lens_model_index(curves: ModelCurves, shell: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray,
                      phases: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each lens' model spots sit in curves.spot_m2 (flattened): (L, 2, 8) indices at eps node 0
    (add node * P * P) and weights (2 field radii x 4 phase neighbours, per frame), and the lens'
    shell index. The model was traced with its field along +x and its lens at (a, b) from the pinhole:
    each lens is mirrored / transposed onto that (its offset from its pinhole; on the disc's centre, its
    field direction), its spots' phases with it."""
    S, R, _, E, P, _ = curves.spot_m2.shape
    k = curves.shell_index(shell)
    v = np.where((curves.offsets[k] == 0).all(axis=1)[:, None], pin_mm, dxy.astype(np.float64))
    sx = np.where(v[:, 0] < 0, -1.0, 1.0)
    sy = np.where(v[:, 1] < 0, -1.0, 1.0)
    swap = np.abs(v[:, 1]) > np.abs(v[:, 0])
    f2 = curves.field_mm ** 2
    r2 = pin_mm[:, 0] ** 2 + pin_mm[:, 1] ** 2
    if R > 1:
        jr = np.clip(np.searchsorted(f2, r2) - 1, 0, R - 2)
        tr = np.clip((r2 - f2[jr]) / (f2[jr + 1] - f2[jr]), 0.0, 1.0)
    else:
        jr, tr = np.zeros(len(k), np.int64), np.zeros(len(k))
    idx = np.zeros((len(k), 2, 8), np.int64)
    wts = np.zeros((len(k), 2, 8))
    for f in range(2):
        px = np.mod(sx * phases[:, 2 * f], 1.0)
        py = np.mod(sy * phases[:, 2 * f + 1], 1.0)
        px, py = np.where(swap, py, px), np.where(swap, px, py)
        ax, ay = px * P, py * P
        x0, y0 = np.floor(ax).astype(np.int64), np.floor(ay).astype(np.int64)
        tx, ty = ax - x0, ay - y0
        c = 0
        for dr, wr in ((0, 1.0 - tr), (1, tr)):
            base = ((k * R + np.minimum(jr + dr, R - 1)) * 2 + f) * E * P * P
            for dy, wy in ((0, 1.0 - ty), (1, ty)):
                for dx, wx in ((0, 1.0 - tx), (1, tx)):
                    idx[:, f, c] = base + ((y0 + dy) % P) * P + (x0 + dx) % P
                    wts[:, f, c] = wr * wy * wx
                    c += 1
    return idx, wts, k


def _lens_model(flat: np.ndarray, idx: np.ndarray, wts: np.ndarray, nodes: np.ndarray, stride: int) -> np.ndarray:
    """(L, K) model D = m2(+u) - m2(-u) of each lens at eps nodes (L, K): its model spots' moments
    (flat[idx + node * stride]) weighted by `wts`, per frame. Compiled: throughfocus_kernels."""
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    if len(idx) and (nodes.min() < 0 or idx.max() + nodes.max() * stride >= flat.size or idx.min() < 0):
        raise ValueError("a lens' model index lies outside the model")  # the kernel reads without bounds checks
    out = np.empty(nodes.shape)
    kern.lens_model_kernel(np.ascontiguousarray(flat, dtype=np.float64), np.ascontiguousarray(idx, dtype=np.int64),
                           np.ascontiguousarray(wts, dtype=np.float64), nodes, int(stride), out)
    return out


BRACKET_NODES = 6  # the lens' own model is read this many eps nodes either side of its first reading
SUBSTEPS = 8  # points per node interval at which the lens' likelihood is summed


def read_traced(curves: ModelCurves, m2: np.ndarray, var: np.ndarray, pos: np.ndarray, shell: np.ndarray,
                dxy: np.ndarray, pin_mm: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radius error, its 1-sigma (before the Birge ratio) and D against the lens' own model at eps = 0
    (px^2) of every lens (all pairs of one |u|; `var`: the variance of its D) on the traced model of its
    own spots (ModelCurves.spot_m2).

    D = m2(+) - m2(-) of a lens is modelled as the model's D at its shell, field radius and its spots'
    sub-pixel positions (`true_phases`), plus the field's orientation term for shells off the disc's
    centre (`field_b`, geometric), plus a constant per shell group: the typical lens' offset from the
    model (a defocus common to all lenses: the sensor's distance; what the model leaves out of the
    blur). The constant is the group's median of D less the lens' model at eps = 0; what remains of a
    sub-pixel pattern beyond the model (fitted on the first harmonic of the phases, robustly, as
    `reference_fit` does) is removed; the lens' D is then read on the phase-averaged model curve (the
    first reading), and then on its own curve between BRACKET_NODES nodes either side of that: the mean
    and sd of eps under the likelihood of its D there."""
    S, R, _, E, P, _ = curves.spot_m2.shape
    eps = curves.eps
    zero = int(np.argmin(np.abs(eps)))
    flat = curves.spot_m2.reshape(-1)
    phases = true_phases(pos, m2, dxy, pin_mm, frame)
    idx, wts, k = _lens_model_index(curves, shell, dxy, pin_mm, phases)
    cos_t = np.array([(a * a - b * b) / (a * a + b * b) if a or b else 0.0 for a, b in curves.offsets])
    r2 = pin_mm[:, 0] ** 2 + pin_mm[:, 1] ** 2
    orient = _interp_rows(r2, curves.field_mm ** 2, curves.field_b, k) * (_cos2(dxy, pin_mm) - cos_t[k])
    d = m2[:, 0] - m2[:, 1] - orient
    c0 = _lens_model(flat, idx, wts, np.full((len(d), 1), zero), P * P)[:, 0]
    grp = _shell_groups(shell)
    ok = np.isfinite(d) & np.isfinite(c0)
    y = d - c0
    resid = y - _group_median(y, grp, ok)
    s0 = max(_robust_sigma(resid[ok]), 1e-12) if ok.sum() >= 2 else np.inf
    keep = ok & (np.abs(resid) <= 4.0 * s0)
    y = y - _pattern_fit(resid, _phase_terms(phases), grp, keep)
    y = y - _group_median(y, grp, keep)  # D against the lens' own model at eps = 0
    x = c0 + y
    # the first reading: the phase-averaged model of its shell and field radius
    avg = curves.spot_m2.mean(axis=(-1, -2))  # (S, R, 2, E)
    avg = avg[:, :, 0] - avg[:, :, 1]  # (S, R, E)
    f2 = curves.field_mm ** 2
    if R > 1:
        jr = np.clip(np.searchsorted(f2, r2) - 1, 0, R - 2)
        tr = np.clip((r2 - f2[jr]) / (f2[jr + 1] - f2[jr]), 0.0, 1.0)[:, None]
        cbar = avg[k, jr] * (1.0 - tr) + avg[k, jr + 1] * tr
    else:
        cbar = avg[k, 0]
    first, slope = _invert_rows(cbar - cbar[:, zero:zero + 1], eps, y)
    # then its own: the mean and sd of eps under the likelihood of x on the lens' own curve, between
    # BRACKET_NODES nodes either side of the first reading (the phase pattern cannot move a reading
    # further): where the curve is steep that is its crossing and the noise over the slope; where a
    # pixel-sized spot's moment stalls over a few % of eps at its phase, the reading is honestly vague
    noise = np.sqrt(np.maximum(var, 0.0) + _extra_variance(y, var, keep))
    j0 = np.clip(np.searchsorted(eps, np.where(np.isfinite(first), first, 0.0)), BRACKET_NODES,
                 E - 1 - BRACKET_NODES)
    nodes = j0[:, None] + np.arange(-BRACKET_NODES, BRACKET_NODES + 1)[None, :]
    own, own_sd = _likelihood_mean(_lens_model(flat, idx, wts, nodes, P * P), eps[nodes], x, noise)
    inside = np.isfinite(own) & (first >= eps[0]) & (first <= eps[-1])  # beyond the model: the first reading
    out = np.where(inside, own, first)
    sigma = np.where(inside, own_sd, noise / np.abs(slope))
    return out, sigma, y


def _extra_variance(y: np.ndarray, var: np.ndarray, keep: np.ndarray) -> float:
    """What the typical lenses' scatter about their own models holds beyond their quoted noise (px^4):
    the robust variance of y over `keep` less the median quoted variance, never below 0."""
    if keep.sum() < 20:
        return 0.0
    return max(_robust_sigma(y[keep]) ** 2 - float(np.median(var[keep])), 0.0)


def _likelihood_mean(cv: np.ndarray, e: np.ndarray, x: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd of e under exp(-(c(e) - x)^2 / 2 noise^2), c the piecewise-linear curve through the
    nodes (cv, e) (L, K) of each row (e equally spaced along a row), summed at SUBSTEPS points per
    interval (flat prior on the span). Compiled: throughfocus_kernels.likelihood_kernel."""
    L = len(cv)
    m1, var = np.empty(L), np.empty(L)
    kern.likelihood_kernel(np.ascontiguousarray(cv, dtype=np.float64), np.ascontiguousarray(x, dtype=np.float64),
                           np.ascontiguousarray(noise, dtype=np.float64), SUBSTEPS, m1, var)
    step = (e[:, 1] - e[:, 0]) / SUBSTEPS
    sd = np.sqrt(np.maximum(var, 0.0)) * step
    return e[:, 0] + m1 * step, np.maximum(sd, step / math.sqrt(12.0))


def _pattern_fit(resid: np.ndarray, terms: np.ndarray, grp: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The significant part of resid's regression on `terms` (group medians removed from the terms),
    robust (twice more without the values beyond 4 sigma); zeros when there are too few values."""
    ok = np.isfinite(resid)
    if keep.sum() < PHASE_MIN_LENSES * (len(np.unique(grp)) + terms.shape[1]):
        return np.zeros(len(resid))
    centred = terms - np.stack([_group_median(t, grp, keep) for t in terms.T], axis=1)
    coef = np.zeros(terms.shape[1])
    for _ in range(3):
        a = centred[keep]
        if len(a) < terms.shape[1] * PHASE_MIN_LENSES or np.linalg.cond(a) > 1e3:
            return np.zeros(len(resid))
        coef, *_ = np.linalg.lstsq(a, resid[keep], rcond=None)
        r = resid - centred @ coef
        keep = ok & (np.abs(r) <= 4.0 * max(_robust_sigma(r[keep]), 1e-12))
    sig = _robust_sigma(resid[keep] - centred[keep] @ coef) * np.sqrt(np.diag(np.linalg.pinv(centred[keep].T @ centred[keep])))
    coef = np.where(np.abs(coef) > 3.0 * sig, coef, 0.0)
    return terms @ coef


# ---------------------------------------------------------------------------------------------- inputs


def _check_inputs(frames, grid: Grid, cfg: CameraConfig):
    """Validate, and group the frames into +u / -u pairs by (|u|, offset): [(u, offset, plus, minus)]."""
    if not isinstance(grid, Grid):
        raise InputError("the through-focus analysis needs the white frame's calibrated Grid")
    if (grid.rows, grid.cols) != (cfg.mla.count_h, cfg.mla.count_w):
        raise InputError(f"the grid has {grid.rows} x {grid.cols} lenses but the camera's MLA has "
                         f"{cfg.mla.count_h} x {cfg.mla.count_w}")
    grid_packing = getattr(grid, "packing", "square")
    if grid_packing != cfg.mla.packing:
        raise InputError(f"the white frame's grid is a {grid_packing} lattice but the camera config's MLA is "
                         f"{cfg.mla.packing} (mla.packing): read the frames with the config of the array they show")
    frames = list(frames)
    if len(frames) < 2:
        raise InputError("a through-focus reading needs at least one +u / -u pair of frames")
    shape = tuple(grid.image_shape)

    def extremes(item) -> tuple[float, float] | None:  # (max, min): NaN propagates through both, +-inf shows
        img = SpotFrame.of(item[1][0]).data if isinstance(item[1], tuple) and len(item[1]) == 2 else None
        if img is None or img.shape != shape or img.dtype.kind not in "fiu":
            return None
        return float(img.max()), float(img.min())

    # a prepared integer frame is normalized by construction and holds no NaN: only other frames are
    # checked whole (their one full pass, a thread per core)
    whole = [k for k, item in enumerate(frames)
             if not (isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], SpotFrame)
                     and item[0].counts)]
    span = dict(zip(whole, thread_map(extremes, [(k, frames[k]) for k in whole])))
    checked = []
    for k, item in enumerate(frames):
        try:
            img, rec = item
        except (TypeError, ValueError):
            raise InputError(f"through-focus frame {k + 1} must be an (image, ThroughFocus) pair") from None
        if not isinstance(rec, ThroughFocus):
            raise InputError(f"through-focus frame {k + 1} has no ThroughFocus record")
        img = SpotFrame.of(img)
        if img.data.ndim != 2 or img.data.dtype.kind not in "fiu":
            raise InputError(f"through-focus frame {k + 1} must be a 2-D numeric image")
        if img.shape != shape:
            raise InputError(f"through-focus frame {k + 1} is {img.shape[1]}x{img.shape[0]} px but the white "
                             f"frame's grid is {shape[1]}x{shape[0]} px")
        if k in span:
            top, bottom = span[k] if span[k] is not None else (float(img.data.max()), float(img.data.min()))
            if not (math.isfinite(top) and math.isfinite(bottom)):
                raise InputError(f"through-focus frame {k + 1} holds NaN or infinite pixels")
            top = (top - img.black) / img.span
            if top > 2.0:
                raise InputError(f"through-focus frame {k + 1} reaches {top:g}, not a normalized frame "
                                 "(white level 1): prepare it with prepare_spots")
        checked.append((img, rec))
    first = checked[0][1]
    for k, (_, rec) in enumerate(checked):
        if rec.f_number != first.f_number or rec.spacing_lenses != first.spacing_lenses:
            raise InputError(f"through-focus frame {k + 1} was taken at f/{rec.f_number:g} with pinholes "
                             f"{rec.spacing_lenses} lenses apart, frame 1 at f/{first.f_number:g} and "
                             f"{first.spacing_lenses}: all frames of a series must share both")
    groups: dict[tuple[float, tuple[int, int]], dict[int, tuple]] = {}
    for k, (img, rec) in enumerate(checked):
        key = (abs(rec.focus_offset_mm), tuple(int(v) for v in rec.offset_lenses))
        sign = 1 if rec.focus_offset_mm > 0 else -1
        slot = groups.setdefault(key, {})
        if sign in slot:
            raise InputError(f"through-focus frames {slot[sign][2] + 1} and {k + 1} are both u = "
                             f"{rec.focus_offset_mm:+g} mm at offset {key[1]}: give each frame once")
        slot[sign] = (img, rec, k)
    pairs = []
    for (u, off), slot in sorted(groups.items()):
        if len(slot) != 2:
            have = next(iter(slot.values()))
            raise InputError(f"through-focus frame {have[2] + 1} (u = {have[1].focus_offset_mm:+g} mm, offset "
                             f"{off}) has no partner of the other sign at the same offset")
        pairs.append((u, off, slot[1], slot[-1]))
    return pairs


EXPOSURE_WINDOWS = 64  # the exposure check looks at about this many of a frame's lit windows, spread over it
NOISE_WINDOWS = 128  # the frame's read noise is the robust spread of about this many windows' rings


def _check_exposure(frame: SpotFrame, sp: Spots, name: str) -> None:
    """The rawio black/saturation checks, on the sub-image windows that should be lit (a pinhole frame
    lights a few per cent of the sensor: the whole frame's percentiles would call it black); every k-th
    window, about EXPOSURE_WINDOWS of them (the statistics of a frame-wide check need no more; each
    spot's own saturation is checked on all of them). A frame of integer counts is checked on its counts
    against its own black and white levels (rawio's histogram statistics), as a white frame is."""
    pick = slice(None, None, max(1, len(sp.cells) // EXPOSURE_WINDOWS))
    n = sp.cells.shape[-1]
    if frame.counts:
        half = n // 2
        cells = np.lib.stride_tricks.sliding_window_view(frame.data, (n, n))[sp.iy[pick] - half, sp.ix[pick] - half]
        black, white = int(round(frame.black)), int(round(frame.black + frame.span))
        bits = min(16, max(8, white.bit_length()))
        check_exposure(RawFrame(np.ascontiguousarray(cells.reshape(-1, n)), bits, None, black, white, source=name))
        return
    flat = np.ascontiguousarray((sp.cells + sp.background[:, None, None])[pick].reshape(-1, n), dtype=np.float32)
    check_exposure(RawFrame(flat, 16, None, 0, 1, source=name, levels_from="normalized"))


# ---------------------------------------------------------------------------------------------- geometry


def coverage(cfg: CameraConfig, tf: ThroughFocus) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For a +u / -u pair at tf's offset: per lens (rows, cols) whether it is fully lit in both frames,
    the index of its nearest pinhole (into `pinhole_lenses`) and its (dx, dy) offset from it in lenses."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    pins = pinhole_lenses(cfg, tf)
    r_in = pair_radius_lenses(cfg, tf)
    m, n = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    if len(pins) == 0 or r_in < 0:
        z = np.zeros((rows, cols), np.int64)
        return np.zeros((rows, cols), bool), z, np.stack([z, z], axis=-1)
    if cfg.mla.packing == "hex":
        return _hex_coverage(cfg, pins, r_in)
    pr, pc = np.unique(pins[:, 0]), np.unique(pins[:, 1])
    if len(pins) == len(pr) * len(pc) and np.array_equal(pins, np.stack(np.meshgrid(pr, pc, indexing="ij"), -1).reshape(-1, 2)):
        # a lattice (row-major, as pinhole_lenses lists it): the nearest pinhole is the nearest row's and
        # column's (the first of equals, as argmin over all of them would pick)
        ir = np.argmin((np.arange(rows)[:, None] - pr[None, :]) ** 2, axis=1)
        ic = np.argmin((np.arange(cols)[:, None] - pc[None, :]) ** 2, axis=1)
        near = ir[:, None] * len(pc) + ic[None, :]
    else:
        near = np.argmin((m[..., None] - pins[:, 0]) ** 2 + (n[..., None] - pins[:, 1]) ** 2, axis=-1)
    dxy = np.stack([n - pins[near, 1], m - pins[near, 0]], axis=-1)
    lit = dxy[..., 0] ** 2 + dxy[..., 1] ** 2 <= r_in * r_in
    return lit, near, dxy


def _hex_coverage(cfg: CameraConfig, pins: np.ndarray, r_in: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`coverage` on a hex array: each lens' nearest pinhole by the Lattice positions (a k-d tree) and its
    (dx, dy) offset in pitches (float: half pitches along x, sqrt(3)/2 along y); lit within r_in."""
    from scipy.spatial import cKDTree

    lat = Lattice("hex", cfg.mla.count_h, cfg.mla.count_w)
    x, y = lat.centres()
    px, py = lat.position(pins[:, 0], pins[:, 1])
    _, near = cKDTree(np.stack([px, py], axis=1)).query(np.stack([x.ravel(), y.ravel()], axis=1))
    near = near.reshape(x.shape).astype(np.int64)
    dxy = np.stack([x - px[near], y - py[near]], axis=-1)
    lit = shell_of(dxy) <= r_in * r_in + 1e-9
    return lit, near, dxy


def shell_of(dxy: np.ndarray) -> np.ndarray:
    """Each lens' shell: its squared distance from its pinhole in pitches^2, an integer on both lattices
    (square dx^2 + dy^2; hex dq^2 + dr^2 + dq dr: 0, 1, 3, 4, 7, ...)."""
    d2 = dxy[..., 0] ** 2 + dxy[..., 1] ** 2
    return d2 if dxy.dtype.kind in "iu" else np.rint(d2).astype(np.int64)


def offset_classes(dxy: np.ndarray) -> np.ndarray:
    """(L,) integer label of each lens' (dx, dy) offset from its pinhole: lenses at the same offset share
    one (hex offsets are counted in half pitches along x and rows along y)."""
    if dxy.dtype.kind not in "iu":
        dxy = np.stack([np.rint(2.0 * dxy[:, 0]), np.rint(dxy[:, 1] / SQRT3_2)], axis=1).astype(np.int64)
    reach = int(np.abs(dxy).max()) if dxy.size else 0
    return (dxy[:, 1] + reach) * (2 * reach + 1) + (dxy[:, 0] + reach)


# --------------------------------------------------------------------------------------------- moments


@dataclass(frozen=True)
class Spots:
    """One frame's windows around L lenses; window pixel coordinates are relative to the centre pixel."""

    cells: np.ndarray  # (L, n, n) background-subtracted
    ix: np.ndarray  # (L,) frame column of the window's centre pixel
    iy: np.ndarray
    background: np.ndarray  # (L,)
    bg_sigma: float  # the frame's unlit-pixel noise (normalized units)
    saturated: np.ndarray  # (L,) bool


def spots(img: SpotFrame | np.ndarray, x_px: np.ndarray, y_px: np.ndarray, half: int) -> Spots:
    """Cut every lens' window (centred on the pixel nearest (x, y), inside the frame), normalized,
    subtract its background (the median of its outer ring) and note saturation. Compiled:
    mlaqc.inspection.throughfocus_kernels.spot_windows_kernel."""
    frame = SpotFrame.of(img)
    ix = np.rint(x_px).astype(np.int64)
    iy = np.rint(y_px).astype(np.int64)
    n, L = 2 * half + 1, len(ix)
    if half <= RING_PX:
        raise ValueError(f"a spot window of half-width {half} px has no pixels inside its {RING_PX}-px ring")
    height, width = frame.shape
    if L and (min(ix.min(), iy.min()) < half or ix.max() + half >= width or iy.max() + half >= height):
        raise ValueError("a spot window reaches past the frame's edge")  # the kernel reads without bounds checks
    cells, bg, sat = np.empty((L, n, n)), np.empty(L, np.float32), np.empty(L, bool)
    kern.spot_windows_kernel(frame.data, iy - half, ix - half, frame.black, frame.span, RING_PX, SATURATED,
                             cells, bg, sat)
    # the frame's unlit-pixel noise: the rings of about NOISE_WINDOWS windows spread over the frame
    ring = np.ones((n, n), bool)
    ring[RING_PX:n - RING_PX, RING_PX:n - RING_PX] = False
    resid = cells[::max(1, L // NOISE_WINDOWS)][:, ring]
    bg_sigma = 1.4826 * float(np.median(np.abs(resid))) if resid.size else 0.0
    return Spots(cells, ix, iy, bg, bg_sigma, sat)


def moments(sp: Spots, cx: np.ndarray, cy: np.ndarray, w: np.ndarray, e_per_unit: float, refine: int = 2,
            variance: bool = True):
    """Centroid (window coordinates), second moment x + y (px^2), its variance and the flux of every
    spot in a window of half-width `w` around (cx, cy); the window follows the centroid `refine` times
    and shrinks so that it stays inside the ring. Pixels at the window's edge weigh by the share of
    them inside it (a row weight times a column weight). The variance is the delta method's
    (d m2 / d v_ij = w_ij (r2_ij - m2) / flux) over the pixels' shot and read noise, plus the ring
    median's. Returns (mx, my, m2, m2_var, flux, w); m2_var is None unless `variance`.
    Compiled: mlaqc.inspection.throughfocus_kernels."""
    L = len(sp.cells)

    def per_lens(v) -> np.ndarray:  # (L,) contiguous float64: one compiled specialization
        return np.ascontiguousarray(np.broadcast_to(np.asarray(v, np.float64), (L,)))

    out = np.empty((L, 6))
    kern.moments_kernel(np.ascontiguousarray(sp.cells, dtype=np.float64), per_lens(sp.background), per_lens(cx),
                        per_lens(cy), per_lens(w), int(refine), float(e_per_unit), float(sp.bg_sigma), RING_PX,
                        bool(variance), out)
    m2_var = out[:, kern.M2_VAR] if variance else None
    return out[:, kern.MX], out[:, kern.MY], out[:, kern.M2], m2_var, out[:, kern.FLUX], out[:, kern.WIDTH]


def _first_guess(sp: Spots) -> tuple[np.ndarray, np.ndarray]:
    """The brightest 3 x 3 sum inside the ring of every window (window coordinates)."""
    out = np.empty((len(sp.cells), 2))
    kern.first_guess_kernel(np.ascontiguousarray(sp.cells, dtype=np.float64), RING_PX, out)
    return out[:, 0], out[:, 1]


def _spot_window(sp: Spots, e_per_unit: float):
    """Each spot's centroid and a window of WINDOW_SIGMAS of its per-axis rms (at least MIN_WINDOW_PX)."""
    cx, cy = _first_guess(sp)
    w = np.full(len(cx), 3.0)
    for _ in range(2):
        cx, cy, m2, _, _, _ = moments(sp, cx, cy, w, e_per_unit, refine=1, variance=False)
        sig = np.sqrt(np.clip(0.5 * np.where(np.isfinite(m2), m2, 1.0), 0.0, None))
        w = np.maximum(WINDOW_SIGMAS * sig, MIN_WINDOW_PX)
    return cx, cy, w


# ------------------------------------------------------------------------------------------- the reading


def _robust_sigma(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _phase_terms(frac: np.ndarray) -> np.ndarray:
    """First Fourier harmonic of the spots' sub-pixel phases, x and y summed (a symmetric spot samples
    alike along both), for both frames: (L, 4). frac: (L, 4) phases of (+x, +y, -x, -y)."""
    a = 2.0 * np.pi * frac
    return np.stack([np.cos(a[:, 0]) + np.cos(a[:, 1]), np.sin(a[:, 0]) + np.sin(a[:, 1]),
                     np.cos(a[:, 2]) + np.cos(a[:, 3]), np.sin(a[:, 2]) + np.sin(a[:, 3])], axis=1)


def _shell_groups(shell: np.ndarray) -> np.ndarray:
    """Group index per lens: its shell, or one pooled group for shells with fewer than MIN_SHELL_LENSES."""
    _, inv, cnt = np.unique(shell, return_inverse=True, return_counts=True)
    return np.unique(np.where(cnt[inv] >= MIN_SHELL_LENSES, inv, -1), return_inverse=True)[1]


def _group_median(v: np.ndarray, grp: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Per lens the median of v over the lenses of its group where `use` (all of the group if none)."""
    out = np.full(v.shape, np.nan)
    for j in np.unique(grp):
        sel = grp == j
        pick = sel & use
        vals = v[pick] if pick.any() else v[sel & np.isfinite(v)]
        if vals.size:
            out[sel] = np.median(vals)
    return out


def reference_fit(m2: np.ndarray, shell: np.ndarray, frac: np.ndarray | None,
                  offset: np.ndarray | None = None) -> np.ndarray:
    """D = m2(+) - m2(-) against its typical value, per lens. m2: (L, 2) second moments of the +u and
    -u spots; frac: (L, 4) their sub-pixel phases (+x, +y, -x, -y), or None; offset: what the typical
    lens' D is known to differ by from lens to lens (the field's, `ModelCurves.field_offset`).

    The typical D is the median of the lens' shell (lenses at its distance from their pinhole, all discs
    and pairs of this |u|; shells with fewer than MIN_SHELL_LENSES lenses pooled). Before that, the
    sub-pixel phase pattern of the typical spots is fitted to what the shells leave (the first harmonic
    of each frame's phases, shell means removed from the terms; robust: twice more without the lenses
    beyond 4 sigma, so defective lenses do not bend it) and removed where it is significant. Its
    amplitude depends on the spot's size, and the fit sees two sizes, the typical +u spot and the
    typical -u spot: a lens' spot is corrected with the amplitude of its own size, linearly between the
    two (held beyond them), so a lens whose focal error swaps the two sizes (c near g) gets the other
    frame's pattern."""
    d = m2[:, 0] - m2[:, 1] - (0.0 if offset is None else offset)
    grp = _shell_groups(shell)
    ok = np.isfinite(d)
    resid = d - _group_median(d, grp, ok)
    s0 = max(_robust_sigma(resid[ok]), 1e-12) if ok.sum() >= 2 else np.inf  # a floor: noise-free frames work
    keep = ok & (np.abs(resid) <= 4.0 * s0)
    corrected = d
    if frac is not None and keep.sum() >= PHASE_MIN_LENSES * (len(np.unique(grp)) + 4):
        terms = _phase_terms(frac)  # (L, 4): (+ cos, + sin, - cos, - sin)
        centred = terms - np.stack([_group_median(t, grp, keep) for t in terms.T], axis=1)
        coef = np.zeros(4)
        for _ in range(3):
            a = centred[keep]
            if len(a) < 4 * PHASE_MIN_LENSES or np.linalg.cond(a) > 1e3:  # the phases do not vary independently of the shells: nothing to fit
                coef[:] = 0.0
                break
            coef, *_ = np.linalg.lstsq(a, resid[keep], rcond=None)
            r = resid - centred @ coef
            keep = ok & (np.abs(r) <= 4.0 * max(_robust_sigma(r[keep]), 1e-12))
        # significant (3 sigma of the coefficients) and physical (a pixel-sized spot: <= 0.3 px^2 per frame)
        sig = _robust_sigma(resid[keep] - centred[keep] @ coef) * np.sqrt(np.diag(np.linalg.pinv(centred[keep].T @ centred[keep])))
        coef = np.where((np.abs(coef) > 3.0 * sig) & (np.abs(coef) < 0.3), coef, 0.0)
        amp_p, amp_m = coef[:2], -coef[2:]  # the m2 patterns of the typical +u and -u spots
        size_p, size_m = np.median(m2[keep, 0]), np.median(m2[keep, 1])
        if abs(size_p - size_m) > 1e-6:
            t = np.clip((m2 - size_m) / (size_p - size_m), 0.0, 1.0)  # (L, 2): 0 = the typical -u size
            amp_plus = amp_m[None, :] + t[:, :1] * (amp_p - amp_m)[None, :]
            amp_minus = amp_m[None, :] + t[:, 1:] * (amp_p - amp_m)[None, :]
        else:
            amp_plus, amp_minus = np.broadcast_to(amp_p, (len(d), 2)), np.broadcast_to(amp_m, (len(d), 2))
        corrected = d - (np.sum(amp_plus * terms[:, :2], axis=1) - np.sum(amp_minus * terms[:, 2:], axis=1))
    return corrected - _group_median(corrected, grp, keep)


def pair_spots(frames: Sequence[tuple[np.ndarray, ThroughFocus]], grid: Grid, cfg: CameraConfig) -> list[dict]:
    """Check the frames (`_check_inputs`) and measure every +u / -u pair's spots: per pair a dict of the
    per-lens arrays of the lenses it reads (flat index, m2 of both frames, D, its variance, spot
    centroids, shell, offset from the pinhole and the pinhole's index)."""
    pairs = _check_inputs(frames, grid, cfg)
    opt = optics(cfg)
    half = int(math.floor(cfg.layout.subimage_pitch_px / 2))
    if half <= RING_PX + 1:
        raise InputError(f"the sub-images are {cfg.layout.subimage_pitch_px:.3g} px apart: the through-focus "
                         f"analysis needs at least {2 * (RING_PX + 2)} px for a spot window inside its background ring")
    h_img, w_img = grid.image_shape
    gx, gy = grid.grid_x_px.ravel(), grid.grid_y_px.ravel()
    with np.errstate(invalid="ignore"):
        inside = (np.isfinite(gx) & np.isfinite(gy) & (np.rint(gx) - half >= 0) & (np.rint(gy) - half >= 0)
                  & (np.rint(gx) + half <= w_img - 1) & (np.rint(gy) + half <= h_img - 1))

    def one(pair) -> dict | None:
        u, off, plus, minus = pair
        lit, near, dxy = coverage(cfg, plus[1])
        idx = np.flatnonzero(lit.ravel() & inside)
        if idx.size == 0:
            return None
        meas = []
        for img, rec, k in (plus, minus):
            sp = spots(img, gx[idx], gy[idx], half)
            name = f"{k + 1} of the through-focus series (u = {rec.focus_offset_mm:+g} mm, offset {off})"
            _check_exposure(img, sp, name)
            if sp.saturated.mean() > 0.5:
                raise InputError(f"Frame {name} is saturated: {int(sp.saturated.sum())} of {len(idx)} spots reach "
                                 "the white level; reduce the exposure or the light")
            meas.append((sp, *_spot_window(sp, opt.e_per_unit)))
        w_common = np.maximum(meas[0][3], meas[1][3])
        res = []
        for sp, cx, cy, _ in meas:
            mx, my, m2, m2_var, flux, _ = moments(sp, cx, cy, w_common, opt.e_per_unit)
            res.append((m2, m2_var, flux, sp.saturated, sp.ix + mx, sp.iy + my))
        (m2p, vp, fp, sp_, xp, yp), (m2m, vm, fm, sm_, xm, ym) = res
        sat = sp_ | sm_
        with np.errstate(invalid="ignore"):  # a lens that throws no spot (missing, opaque): not read
            lit_p, lit_m = fp > MIN_FLUX * np.nanmedian(fp), fm > MIN_FLUX * np.nanmedian(fm)
        good = np.isfinite(m2p) & np.isfinite(m2m) & np.isfinite(vp) & np.isfinite(vm) & lit_p & lit_m & ~sat
        pos = np.stack([xp, yp, xm, ym], axis=1)[good]
        return dict(u=u, off=off, rec=plus[1], idx=idx[good], d=(m2p - m2m)[good], var=(vp + vm)[good],
                    m2=np.stack([m2p, m2m], axis=1)[good],
                    shell=shell_of(dxy).ravel()[idx[good]],
                    dxy=dxy.reshape(-1, 2)[idx[good]], pin=near.ravel()[idx[good]], pos=pos,
                    grid_xy=np.stack([gx[idx[good]], gy[idx[good]]], axis=1),
                    saturated=int(sat.sum()), window=float(np.median(w_common)))

    # the pairs are independent and NumPy lets go of the GIL in the array work: one thread per core
    # (results in the pairs' order, and the first pair's error first, as a loop would raise it)
    got = [p for p in thread_map(one, pairs) if p is not None]
    if not got or sum(len(p["idx"]) for p in got) == 0:
        raise InputError("no lens is fully lit (and unsaturated) in both frames of any +u / -u pair: check the "
                         "pinhole offsets, the focus offset u and the exposure")
    return got


def measure_through_focus(frames: Sequence[tuple[np.ndarray, ThroughFocus]], grid: Grid, cfg: CameraConfig,
                          *, model: str = "traced") -> ThroughFocusResult:
    """Every microlens' focal-length error (with its sign) and optical-centre displacement from prepared
    through-focus frames (`prepare_spots`), each with its ThroughFocus record, on the white frame's `grid`
    (see the module note). `model`: 'traced' reads D on the camera's traced D(eps) (aberrations
    included), 'paraxial' on the paraxial one (spots that are scaled apertures). Raises InputError on
    frames that do not fit the grid, pairs without both signs, records that disagree, black or saturated
    frames, or when no lens is fully lit in any pair."""
    t0 = time.perf_counter()
    if model not in ("traced", "paraxial"):
        raise InputError(f"the through-focus model must be 'traced' or 'paraxial', not {model!r}")
    got = pair_spots(frames, grid, cfg)
    opt = optics(cfg)
    rows, cols = grid.rows, grid.cols
    t_moments = time.perf_counter() - t0

    # D against the typical lens of its shell (the main lens' field effects on it removed), phase
    # pattern removed, per |u| (all pairs of that u), read on the model's D(eps)
    for u in sorted({p["u"] for p in got}):
        group = [p for p in got if p["u"] == u]
        shells = np.unique(np.concatenate([p["shell"] for p in group]))
        curves = (model_curves(cfg, u, group[0]["rec"].f_number, pair_radius_lenses(cfg, group[0]["rec"]))
                  if model == "traced" else paraxial_curves(cfg, u, shells))
        pin_mm = [lens_centres_mm(cfg, pinhole_lenses(cfg, p["rec"])[p["pin"]]) for p in group]
        cat = {k: np.concatenate([p[k] for p in group]) for k in ("m2", "var", "pos", "shell", "dxy")}
        if model == "traced":
            frame_of = np.concatenate([np.full(len(p["d"]), j) for j, p in enumerate(group)])
            eps_all, sig_all, rel = read_traced(curves, cat["m2"], cat["var"], cat["pos"], cat["shell"], cat["dxy"],
                                                np.concatenate(pin_mm), frame_of)
        else:
            field_d = np.concatenate([curves.field_offset(p["shell"], p["dxy"], q) for p, q in zip(group, pin_mm)])
            rel = reference_fit(cat["m2"], cat["shell"], cat["pos"] - np.rint(cat["pos"]), field_d)
            eps_all, slope_all = _invert(curves, cat["shell"], rel)
            sig_all = np.sqrt(cat["var"]) / np.abs(slope_all)
        start = 0
        for p in group:
            sl = slice(start, start + len(p["d"]))
            start += len(p["d"])
            p["rel"], p["eps"] = rel[sl], eps_all[sl]
            p["eps_sig"] = sig_all[sl]
            p["gain"] = curves.gain
    t_model = time.perf_counter() - t0 - t_moments

    readings = []
    num, den, dsum = np.zeros(rows * cols), np.zeros(rows * cols), np.zeros(rows * cols)
    birge = {}
    for u in {p["u"] for p in got}:  # the Birge ratio of each |u|: all its pairs' lenses
        z = np.concatenate([p["eps"] / p["eps_sig"] for p in got if p["u"] == u])
        k = _robust_sigma(z) if np.isfinite(z).sum() >= 20 else 1.0
        birge[u] = max(1.0, k if np.isfinite(k) else 1.0)
    for p in got:
        ok = np.isfinite(p["eps"]) & np.isfinite(p["eps_sig"]) & (p["eps_sig"] > 0)
        k = birge[p["u"]]
        wgt = 1.0 / (k * p["eps_sig"][ok]) ** 2
        np.add.at(num, p["idx"][ok], wgt * p["eps"][ok])
        np.add.at(den, p["idx"][ok], wgt)
        np.add.at(dsum, p["idx"][ok], wgt * p["rel"][ok])
        readings.append(PairReading(float(p["u"]), p["off"], int(ok.sum()), opt.g(p["u"]), opt.g(-p["u"]),
                                    float(p["gain"]), float(k), p["window"], p["saturated"]))
    covered = (den > 0).reshape(rows, cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        eps = np.where(den > 0, num / den, np.nan).reshape(rows, cols)
        eps_sig = np.where(den > 0, 1.0 / np.sqrt(den), np.nan).reshape(rows, cols)
        delta = np.where(den > 0, dsum / den, np.nan).reshape(rows, cols)
    focal = focal_rel_of_radius(cfg, eps)
    dfde = (focal_rel_of_radius(cfg, eps + 1e-4) - focal_rel_of_radius(cfg, eps - 1e-4)) / 2e-4
    cdx, cdy, csig = _centres(got, rows, cols, opt, cfg)
    return ThroughFocusResult(focal, eps_sig * np.abs(dfde), eps, covered, delta, cdx, cdy, csig, tuple(readings),
                              cfg.layout.micro.efl * 1e3,
                              {"moments": round(t_moments, 4), "model": round(t_model, 4),
                               "total": round(time.perf_counter() - t0, 4)})


def _centres(got: list[dict], rows: int, cols: int, opt: Optics, cfg: CameraConfig):
    """Optical-centre displacement per lens (µm, MLA plane): each frame's spot centroid minus its white
    sub-image centre, minus the median of the lenses at the same (dx, dy) from their pinhole (all frames
    of that signed u: the main lens' aberrations over a disc), minus each frame's constant (the mask's
    placement) and a smooth field common to the frames of that u (`_field_removed`: the main lens'
    distortion); averaged over the lens' frames; sigma from the residuals' spread (`_clipped_rms`)."""
    by_u: dict[float, list] = {}
    for p in got:
        by_u.setdefault(p["u"], []).append((p, 0))
        by_u.setdefault(-p["u"], []).append((p, 2))
    sx, sy, cnt = np.zeros(rows * cols), np.zeros(rows * cols), np.zeros(rows * cols)
    resid_all = []
    for u, items in by_u.items():
        cls = offset_classes(np.concatenate([p["dxy"] for p, _ in items]))
        pins = [lens_centres_mm(cfg, pinhole_lenses(cfg, p["rec"])[p["pin"]]) for p, _ in items]
        lens = [lens_centres_mm(cfg, np.stack(np.divmod(p["idx"], cols), axis=1)) for p, _ in items]
        # the paraxial chief ray through the lens' centre from the pinhole's image, against the white
        # sub-image centre (the chief ray from the exit pupil): what is left is the same for every disc
        pred = [((xp - xl) * (opt.s_mm / opt.u_prime(u)) - xl * (opt.s_mm / opt.pupil_mm)) / opt.pixel_mm
                for xp, xl in zip(pins, lens)]
        ox = _class_centred(np.concatenate([p["pos"][:, j] - p["grid_xy"][:, 0] - q[:, 0]
                                            for (p, j), q in zip(items, pred)]), cls)
        oy = _class_centred(np.concatenate([p["pos"][:, j + 1] - p["grid_xy"][:, 1] - q[:, 1]
                                            for (p, j), q in zip(items, pred)]), cls)
        frame_of = np.concatenate([np.full(len(p["idx"]), j) for j, (p, _) in enumerate(items)])
        pin_all = np.concatenate(pins)
        rx, ry = (_field_removed(v, pin_all, frame_of) for v in (ox, oy))
        idx = np.concatenate([p["idx"] for p, _ in items])
        ok = np.isfinite(rx) & np.isfinite(ry)
        np.add.at(sx, idx[ok], rx[ok])
        np.add.at(sy, idx[ok], ry[ok])
        np.add.at(cnt, idx[ok], 1.0)
        resid_all.append(np.concatenate([rx[ok], ry[ok]]))
    um = opt.pixel_mm * 1e3 / (1.0 - opt.c0)  # µm in the MLA plane per px of spot motion
    spread = _clipped_rms(np.concatenate(resid_all)) if resid_all else float("nan")
    with np.errstate(invalid="ignore", divide="ignore"):
        dx = np.where(cnt > 0, sx / cnt, np.nan).reshape(rows, cols) * um
        dy = np.where(cnt > 0, sy / cnt, np.nan).reshape(rows, cols) * um
        sig = np.where(cnt > 0, spread / np.sqrt(np.maximum(cnt, 1)), np.nan).reshape(rows, cols) * um
    return dx, dy, sig


def _clipped_rms(r: np.ndarray) -> float:
    """RMS of r within 5 robust sigma: the tails of pixel sampling counted, displaced lenses not."""
    r = r[np.isfinite(r)]
    if r.size < 2:
        return float("nan")
    keep = np.abs(r - np.median(r)) <= 5.0 * max(_robust_sigma(r), 1e-12)
    return float(np.sqrt(np.mean(r[keep] ** 2)))


def _least_squares(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin |a x - b| for a tall, well-scaled a (a few columns): the normal equations (SVD-based lstsq
    where they are singular)."""
    try:
        return np.linalg.solve(a.T @ a, a.T @ b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]


def _field_removed(v: np.ndarray, xy: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """v minus its robust least-squares fit on a constant per frame (the mask's placement) plus a
    polynomial of the pinhole positions xy (L, 2) common to all frames of this u (the main lens'
    distortion; quadratic, cubic from 200 values): twice more without the values beyond 4 sigma. The
    frames' constants are eliminated first (the polynomial is fitted to values and terms less their
    frame's means, then each constant is its frame's mean residual: the same least squares)."""
    ok = np.isfinite(v)
    if not ok.any():
        return v
    scale = max(float(np.max(np.abs(xy))), 1e-12)  # terms of order 1: the normal equations stay well conditioned
    x, y = xy[:, 0] / scale, xy[:, 1] / scale
    frames, f = np.unique(frame, return_inverse=True)
    nf = len(frames)
    cols = [x, y, x * x, x * y, y * y]
    if ok.sum() >= 200:
        cols += [x ** 3, x * x * y, x * y * y, y ** 3]
    a = np.stack(cols, axis=1)
    vz = np.where(ok, v, 0.0)
    keep = ok.copy()
    out = v - np.median(v[ok])
    for _ in range(3):
        if keep.sum() <= a.shape[1] + nf:
            break
        fk = f[keep]
        n = np.maximum(np.bincount(fk, minlength=nf), 1).astype(np.float64)
        ak = a[keep]
        # each frame's sums of terms and values
        sums = np.stack([np.bincount(fk, weights=c, minlength=nf) for c in (*ak.T, vz[keep])], axis=1)
        am, vm = sums[:, :-1] / n[:, None], sums[:, -1] / n
        beta = _least_squares(ak - am[fk], vz[keep] - vm[fk])
        out = v - (vm - am @ beta)[f] - a @ beta
        keep = ok & (np.abs(out) <= 4.0 * max(_robust_sigma(out[keep]), 1e-12))
    return out


def _class_centred(v: np.ndarray, cls: np.ndarray, min_count: int = MIN_SHELL_LENSES) -> np.ndarray:
    """v minus the median of its class; classes with fewer than `min_count` members become NaN."""
    out = np.full(v.shape, np.nan)
    ok = np.isfinite(v)
    if not ok.any():
        return out
    labels, inv, cnt = np.unique(cls[ok], return_inverse=True, return_counts=True)
    from scipy import ndimage

    med = np.asarray(ndimage.median(v[ok], cls[ok], labels), dtype=np.float64)
    vals = v[ok] - med[inv]
    vals[cnt[inv] < min_count] = np.nan
    out[ok] = vals
    return out


__all__ = ["ThroughFocusResult", "PairReading", "ModelCurves", "measure_through_focus", "prepare_spots",
           "model_curves", "paraxial_curves", "optics", "aperture_moment_mm2", "coverage", "pair_radius_lenses",
           "focal_rel_of_radius", "reference_fit", "read_traced", "true_phases", "pair_spots", "trace_model",
           "model_key", "save_model", "load_model"]
