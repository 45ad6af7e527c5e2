"""White plenoptic frames from an analytic model that shares no code with mlaqc's tracer.

Each sub-image is a disc (the main lens' pupil imaged by one microlens) whose rim is blurred by a
Gaussian or an Airy edge-spread function, on a rotated square or hexagonal grid (hex: rows pitch·√3/2
apart, every second row shifted half a pitch right; a radius under half the pitch leaves gaps) with any
sub-pixel phase, integrated exactly
over each pixel (4 x 4 Gauss-Legendre points: the disc is smooth at that scale), times cos⁴ vignetting
(and an optional extra radial fall-off), a fixed PRNU pattern and nearest-neighbour crosstalk; an
optional uniform background stands for the unfocused light that clear gaps between circular lenses let
through. A circular lens aperture smaller than its cell (`aperture_rel`) leaves the sub-image the main
lens' pupil disc (every lens still sees the whole pupil), dimmer alike for every lens (exposure takes
that up), and widens its rim by the smaller aperture's diffraction. Seeded
anomalies of known size: shift, skew (intensity tilt), blur, size, dim, missing. Noise from none to
15 % per white pixel; containers of 8, 12 (in 16), 14 and 16 bits with black levels and with or
without level tags.

What it neglects on purpose: the main lens' aberrations and the microlens' own focus (a disc with a
symmetric rim, where the tracer's sub-images carry spherical aberration), and diffraction in the pupil
plane (the rim ESF stands for all blur). It is a different generator, not a better one: inspection must
hold on both. Coordinates: x = column, y = row, (0, 0) the centre of the top-left pixel; lens (m, n) is
row m from the top, column n from the left (0-based here); directions counterclockwise from +x towards
the image top (90° = up, smaller row).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.special import erfc, j1

# Table 1 (the paper; DESIGN.md): microlens pitch 100 µm, microlens focal length ≈ 0.4204 mm, MLA
# 176.55 mm behind the main lens' exit pupil, 5 µm pixels. Sub-image pitch p(b+f)/b in pixels; the
# f-number-matched pupil image fills the cell, so the disc radius is half of that pitch.
TABLE1_PITCH_UM, TABLE1_F_MM, TABLE1_B_MM, TABLE1_PIXEL_UM = 100.0, 0.42036, 176.55066, 5.0
GL_NODES = np.array([-0.4305681557970263, -0.16999052179242813, 0.16999052179242813, 0.4305681557970263])
GL_WEIGHTS = np.array([0.17392742256872692, 0.3260725774312731, 0.3260725774312731, 0.17392742256872692])
KINDS = ("shift", "skew", "blur", "size", "dim", "missing")


def table1_pitch_px() -> float:
    """Sub-image pitch of the Table 1 camera: p (b + f) / b over the pixel size (≈ 20.048 px)."""
    return TABLE1_PITCH_UM * (TABLE1_B_MM + TABLE1_F_MM) / TABLE1_B_MM / TABLE1_PIXEL_UM


@dataclass(frozen=True)
class Anomaly:
    """One seeded anomaly on lens (row, col), 0-based. magnitude: shift px, skew relative tilt over the
    radius, blur factor on the rim sigma, size factor on the radius, dim factor on the flux; spot (not in
    KINDS: a dust shadow) the light lost over a round patch covering `area` of the disc, its centre towards
    `direction_deg` as far out as the disc holds it; scratch (not in KINDS) the light lost along a line
    `width_px` wide and `length_px` long through the lens' sub-image centre at `direction_deg` (it moves with
    the array and may run on through the neighbours' sub-images)."""

    row: int
    col: int
    kind: str
    magnitude: float
    direction_deg: float = 0.0
    area: float = 0.25
    length_px: float = 0.0
    width_px: float = 1.5


@dataclass(frozen=True)
class SensorSpot:
    """A shadow on the sensor (dust on its cover glass): the light lost (`depth`) over a round patch of
    `radius_px` centred at (x_px, y_px) in frame pixels, wherever the array sits."""

    x_px: float
    y_px: float
    radius_px: float
    depth: float


@dataclass(frozen=True)
class AnalyticModel:
    """A white frame's parameters; `render()` gives the noise-free irradiance (≈ 1 at the centre)."""

    shape: tuple[int, int] = (2048, 2048)
    lenses: tuple[int, int] = (102, 102)
    pitch_px: float = field(default_factory=table1_pitch_px)
    radius_px: float = 9.75
    rotation_deg: float = 0.0
    phase_px: tuple[float, float] = (0.0, 0.0)  # offset of the array centre from the frame centre
    rim: str = "gaussian"  # or "airy"
    rim_sigma_px: float = 0.5  # Gaussian ESF sigma
    airy_radius_px: float = 0.64  # first zero of the Airy PSF, 1.22 λ N (Table 1 at 632.8 nm)
    exit_pupil_px: float = 3700.0  # cos⁴ vignetting: chief-ray angle atan(distance / this)
    extra_falloff: float = 0.0  # times 1 - k (r / r_corner)²
    prnu_rms: float = 0.005
    crosstalk: float = 0.02  # to each 4-neighbour
    sensor_seed: int = 3
    anomalies: tuple[Anomaly, ...] = ()
    packing: str = "square"  # or "hex": rows pitch·√3/2 apart, rows 1, 3, ... (0-based; U(2,n), U(4,n), ...) +pitch/2 in x
    background: float = 0.0  # unfocused light through clear gaps between circular lenses, level under and between discs
    aperture_rel: float = 1.0  # the lens aperture: 1 fills its cell; < 1 a circle of this diameter over the pitch
    sensor_spots: tuple[SensorSpot, ...] = ()  # shadows fixed on the sensor, not on the array
    resize_keeps_flux: bool = False  # a 'size' anomaly keeps the lens' light (the pupil's image rescaled by a
    # focal or axial error: the same light over another area), not its level (the default, as before)

    def with_anomalies(self, anomalies) -> AnalyticModel:
        return dataclasses.replace(self, anomalies=tuple(anomalies))

    def lattice(self) -> tuple[np.ndarray, np.ndarray]:
        """Undisturbed lens centres (x, y), each (rows, cols); the middle of their bounding box (before the
        rotation) sits at the frame centre + phase_px."""
        rows, cols = self.lenses
        a = math.radians(self.rotation_deg)  # counterclockwise on the image (towards the top)
        if self.packing == "hex":
            m, n = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
            shifted = 0.5 if rows > 1 else 0.0
            u = (n + 0.5 * (m % 2) - (cols - 1 + shifted) / 2) * self.pitch_px
            v = (m - (rows - 1) / 2) * (math.sqrt(3.0) / 2) * self.pitch_px
        elif self.packing == "square":
            m, n = np.meshgrid(np.arange(rows) - (rows - 1) / 2, np.arange(cols) - (cols - 1) / 2, indexing="ij")
            u, v = n * self.pitch_px, m * self.pitch_px
        else:
            raise ValueError(f"unknown packing {self.packing!r}")
        x = (self.shape[1] - 1) / 2 + self.phase_px[0] + u * math.cos(a) + v * math.sin(a)
        y = (self.shape[0] - 1) / 2 + self.phase_px[1] - u * math.sin(a) + v * math.cos(a)
        return x, y

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """True sub-image centres (x, y), shifts included."""
        x, y = self.lattice()
        x, y = x.copy(), y.copy()
        for a in self.anomalies:
            if a.kind == "shift":
                t = math.radians(a.direction_deg)
                x[a.row, a.col] += a.magnitude * math.cos(t)
                y[a.row, a.col] -= a.magnitude * math.sin(t)
        return x, y

    def inside(self) -> np.ndarray:
        """Lenses whose whole disc lies on the sensor."""
        x, y = self.centres()
        r = self.radius_px + 2
        return (x >= r) & (y >= r) & (x <= self.shape[1] - 1 - r) & (y <= self.shape[0] - 1 - r)

    def render(self) -> np.ndarray:
        """Noise-free irradiance (float64, H x W)."""
        x, y = self.centres()
        rows, cols = self.lenses
        radius = np.full((rows, cols), self.radius_px)
        blur = np.ones((rows, cols))
        flux = np.ones((rows, cols))
        skew = np.zeros((rows, cols, 2))
        for a in self.anomalies:
            k = (a.row, a.col)
            t = math.radians(a.direction_deg)
            if a.kind == "size":
                radius[k] *= a.magnitude
                if self.resize_keeps_flux:
                    flux[k] /= a.magnitude ** 2
            elif a.kind == "blur":
                blur[k] *= a.magnitude
            elif a.kind == "dim":
                flux[k] *= a.magnitude
            elif a.kind == "missing":
                flux[k] = 0.0
            elif a.kind == "skew":
                skew[k] = (a.magnitude * math.cos(t), -a.magnitude * math.sin(t))
        img = np.zeros(self.shape)
        edge = self._edge()
        for chunk in np.array_split(np.arange(rows * cols), max(1, rows * cols // 1500)):
            self._add_discs(img, x.ravel()[chunk], y.ravel()[chunk], radius.ravel()[chunk], blur.ravel()[chunk],
                            flux.ravel()[chunk], skew.reshape(-1, 2)[chunk], edge)
        for a in self.anomalies:
            if a.kind == "spot":
                self._darken_spot(img, x[a.row, a.col], y[a.row, a.col], a)
            elif a.kind == "scratch":
                self._darken_line(img, x[a.row, a.col], y[a.row, a.col], a)
        for s in self.sensor_spots:
            _darken_disc(img, s.x_px, s.y_px, s.radius_px, s.depth)
        if self.background:
            img += self.background
        img *= self._vignetting()
        if self.crosstalk:
            c = self.crosstalk
            out = (1 - 4 * c) * img
            out[1:] += c * img[:-1]
            out[:-1] += c * img[1:]
            out[:, 1:] += c * img[:, :-1]
            out[:, :-1] += c * img[:, 1:]
            img = out
        if self.prnu_rms:
            img *= 1.0 + np.random.default_rng(self.sensor_seed).normal(0.0, self.prnu_rms, self.shape)
        return img

    def _darken_spot(self, img, cx: float, cy: float, a: Anomaly) -> None:
        """Multiply the pixels of a round patch (area `a.area` of the disc, its edge smoothed over half a
        pixel) by 1 - depth, the patch as far out towards `a.direction_deg` as the disc holds it."""
        rho = self.radius_px * math.sqrt(a.area)
        d = max(0.0, 0.95 * self.radius_px - rho)
        t = math.radians(a.direction_deg)
        _darken_disc(img, cx + d * math.cos(t), cy - d * math.sin(t), rho, a.magnitude)

    def _darken_line(self, img, cx: float, cy: float, a: Anomaly) -> None:
        """Multiply the pixels within `a.width_px / 2` of a segment `a.length_px` long through (cx, cy) at
        `a.direction_deg` by 1 - depth (edges smoothed over half a pixel)."""
        t = math.radians(a.direction_deg)
        ux, uy = math.cos(t), -math.sin(t)
        r = int(math.ceil(a.length_px / 2 + a.width_px + 2))
        y0, x0 = int(round(cy)) - r, int(round(cx)) - r
        yy, xx = np.mgrid[y0:y0 + 2 * r + 1, x0:x0 + 2 * r + 1]
        along = (xx - cx) * ux + (yy - cy) * uy
        across = np.abs(-(xx - cx) * uy + (yy - cy) * ux)
        inside = (0.5 * erfc((across - a.width_px / 2) / 0.5)) * (0.5 * erfc((np.abs(along) - a.length_px / 2) / 0.5))
        _apply(img, yy, xx, 1.0 - a.magnitude * inside)

    def _edge(self):
        """The rim's edge-spread function of the signed distance inside the rim (px) and a blur factor."""
        if self.rim == "gaussian":
            return lambda d, b: 0.5 * erfc(-d / (math.sqrt(2.0) * self.rim_sigma() * b))
        if self.rim == "airy":
            return _airy_esf(self.airy_px())
        raise ValueError(f"unknown rim {self.rim!r}")

    def airy_px(self) -> float:
        """The Airy PSF's first zero (px) behind this lens aperture: 1.22 λ f / D grows as D shrinks."""
        return self.airy_radius_px / self.aperture_rel

    def rim_sigma(self) -> float:
        """The Gaussian rim's sigma (px): `rim_sigma_px` for a lens filling its cell; a smaller circular
        aperture widens its diffraction share (the Airy core's sigma, 0.42 λ f / D = 0.344 of its first
        zero) in quadrature."""
        if self.aperture_rel == 1.0:
            return self.rim_sigma_px
        diffraction = 0.344 * self.airy_radius_px
        return math.sqrt(self.rim_sigma_px ** 2 + diffraction ** 2 * (1.0 / self.aperture_rel ** 2 - 1.0))

    def _add_discs(self, img, cx, cy, radius, blur, flux, skew, edge) -> None:
        """Sum the pixel integrals of discs centred at (cx, cy) into img (vectorized over lenses)."""
        h, w = img.shape
        half = int(math.ceil(self.radius_px * 1.25 + 4 * max(self.rim_sigma(), self.airy_px()) * blur.max()))
        off = np.arange(-half, half + 1)
        px = np.rint(cx)[:, None, None] + off[None, None, :]
        py = np.rint(cy)[:, None, None] + off[None, :, None]
        val = np.zeros(np.broadcast_shapes(px.shape, py.shape))
        for i, wy in zip(GL_NODES, GL_WEIGHTS):
            dy = py + i - cy[:, None, None]
            for j, wx in zip(GL_NODES, GL_WEIGHTS):
                dx = px + j - cx[:, None, None]
                d = radius[:, None, None] - np.hypot(dx, dy)
                tilt = 1.0 + (skew[:, 0, None, None] * dx + skew[:, 1, None, None] * dy) / radius[:, None, None]
                val += wy * wx * edge(d, blur[:, None, None]) * tilt
        val *= flux[:, None, None]
        px, py = np.broadcast_to(px, val.shape), np.broadcast_to(py, val.shape)
        ok = (px >= 0) & (px < w) & (py >= 0) & (py < h) & (val != 0)
        idx = (py[ok] * w + px[ok]).astype(np.int64)
        img += np.bincount(idx, weights=val[ok], minlength=h * w).reshape(h, w)

    def _vignetting(self) -> np.ndarray:
        h, w = self.shape
        y, x = np.ogrid[:h, :w]
        r2 = (x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2
        out = 1.0 / (1.0 + r2 / self.exit_pupil_px ** 2) ** 2
        if self.extra_falloff:
            out = out * (1.0 - self.extra_falloff * r2 / ((w / 2) ** 2 + (h / 2) ** 2))
        return out


def _darken_disc(img, sx: float, sy: float, rho: float, depth: float) -> None:
    """Multiply the pixels of a round patch of radius `rho` at (sx, sy) by 1 - depth (edge smoothed over half
    a pixel)."""
    r = int(math.ceil(rho + 2))
    y0, x0 = int(round(sy)) - r, int(round(sx)) - r
    yy, xx = np.mgrid[y0:y0 + 2 * r + 1, x0:x0 + 2 * r + 1]
    _apply(img, yy, xx, 1.0 - depth * 0.5 * erfc((np.hypot(xx - sx, yy - sy) - rho) / 0.5))


def _apply(img, yy, xx, factor) -> None:
    """img[yy, xx] *= factor where (yy, xx) lies on the frame."""
    ok = (yy >= 0) & (yy < img.shape[0]) & (xx >= 0) & (xx < img.shape[1])
    img[yy[ok], xx[ok]] *= factor[ok]


def _airy_esf(airy_radius_px: float):
    """Edge-spread function of an Airy PSF (first zero at airy_radius_px): the line-spread function is
    the PSF integrated along the edge, the ESF its running integral; tabulated and interpolated."""
    k = 3.8317059702 / airy_radius_px  # first zero of J1
    t = np.linspace(-12 * airy_radius_px, 12 * airy_radius_px, 2401)
    s = np.linspace(0, 40 * airy_radius_px, 8001)
    rho = np.hypot(t[:, None], s[None, :])
    v = np.maximum(k * rho, 1e-12)
    psf = (2 * j1(v) / v) ** 2
    lsf = np.trapezoid(psf, s, axis=1)
    esf = np.concatenate([[0.0], np.cumsum(0.5 * (lsf[1:] + lsf[:-1]) * np.diff(t))])
    esf /= esf[-1]

    def edge(d, b):
        return np.interp(d / b, t, esf)

    return edge


def random_anomalies(model: AnalyticModel, count: int, rng: np.random.Generator, kinds=KINDS,
                     margin: int = 3) -> list[Anomaly]:
    """`count` anomalies of random kind, magnitude and direction on lenses at least `margin` lenses in from
    the edge and two lenses apart. Magnitudes are well above what a 15 % noise frame hides."""
    rows, cols = model.lenses
    taken = np.zeros((rows, cols), bool)
    out = []
    sizes = {"shift": (0.25, 0.8), "skew": (0.15, 0.3), "blur": (2.0, 3.0), "size": (0.85, 0.92),
             "dim": (0.6, 0.8), "missing": (0.0, 0.0)}
    while len(out) < count:
        m, n = int(rng.integers(margin, rows - margin)), int(rng.integers(margin, cols - margin))
        if taken[m - 2:m + 3, n - 2:n + 3].any():
            continue
        taken[m, n] = True
        kind = kinds[len(out) % len(kinds)]
        lo, hi = sizes[kind]
        out.append(Anomaly(m, n, kind, float(rng.uniform(lo, hi)), float(rng.uniform(0, 360))))
    return out


def expose(irradiance: np.ndarray, noise_rel: float, rng: np.random.Generator) -> np.ndarray:
    """Signal with shot noise of `noise_rel` at signal 1 (scaling as its square root) and read noise of
    noise_rel / 20; noise_rel = 0 returns the input exactly."""
    if noise_rel <= 0:
        return np.asarray(irradiance, dtype=np.float64)
    s = np.clip(irradiance, 0, None)
    return s + noise_rel * np.sqrt(s) * rng.standard_normal(s.shape) + noise_rel / 20 * rng.standard_normal(s.shape)


def to_counts(signal: np.ndarray, bits: int, black: int = 0, white_fraction: float = 0.8) -> np.ndarray:
    """Counts: signal 1 at black + white_fraction of the range above black; uint8 up to 8 bits, else uint16."""
    top = (1 << bits) - 1
    counts = np.clip(np.rint(black + signal * white_fraction * (top - black)), 0, top)
    return counts.astype(np.uint8 if bits <= 8 else np.uint16)


def write_container(path: str | Path, counts: np.ndarray, bits: int, black: int, tags: bool = True) -> Path:
    """A TIFF (with DNG-style BlackLevel/WhiteLevel tags if `tags`), PNG or NPY of the counts, as a
    camera or another tool would write them (no mlaqc record)."""
    import tifffile

    path = Path(path)
    if path.suffix in (".tif", ".tiff"):
        extra = [(50714, 4, 1, black, False), (50717, 4, 1, (1 << bits) - 1, False)] if tags else []
        tifffile.imwrite(path, counts, extratags=extra)
    elif path.suffix == ".png":
        import cv2

        cv2.imwrite(str(path), counts)
    elif path.suffix == ".npy":
        np.save(path, counts)
    else:
        raise ValueError(f"unknown container {path.suffix}")
    return path


@dataclass(frozen=True)
class DarkPattern:
    """A camera's fixed dark pattern, in counts above the black level: amplifier glow in one corner
    (`glow_dn` at the corner pixel, falling off as exp(-r / (glow_scale x the frame's smaller side)) with
    r from a point just outside the corner),
    a random offset per column (uniform within ±`column_dn`) and `hot` hot pixels (dark excess
    log-uniform in `hot_dn`). What `dark_frame` adds read noise to, and what a white frame carries too."""

    shape: tuple[int, int] = (2048, 2048)
    glow_dn: float = 400.0
    glow_scale: float = 0.08
    column_dn: float = 6.0
    hot: int = 2000
    hot_dn: tuple[float, float] = (40.0, 3000.0)
    seed: int = 17

    def hot_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the hot pixels, distinct."""
        rng = np.random.default_rng(self.seed)
        flat = rng.choice(self.shape[0] * self.shape[1], size=self.hot, replace=False)
        return np.unravel_index(np.sort(flat), self.shape)

    def level(self) -> np.ndarray:
        """The pattern (float64, H x W), counts above black."""
        h, w = self.shape
        rng = np.random.default_rng(self.seed + 1)
        y, x = np.ogrid[:h, :w]
        scale = self.glow_scale * min(h, w)
        d = 0.5 * scale  # the amplifier sits just outside the top-right corner: the corner pixel gets glow_dn
        out = self.glow_dn * np.exp(-(np.hypot(x - (w - 1) - d, y + d) - np.sqrt(2) * d) / scale)
        out = out + rng.uniform(-self.column_dn, self.column_dn, w)[None, :]
        r, c = self.hot_pixels()
        lo, hi = self.hot_dn
        out[r, c] += np.exp(rng.uniform(np.log(lo), np.log(hi), r.size))
        return out


def dark_frame(pattern: np.ndarray, read_noise_dn: float, rng: np.random.Generator, bits: int, black: int) -> np.ndarray:
    """One dark frame's counts: black + the pattern + Gaussian read noise, rounded and clipped to `bits`."""
    counts = black + pattern + read_noise_dn * rng.standard_normal(pattern.shape)
    return np.clip(np.rint(counts), 0, (1 << bits) - 1).astype(np.uint8 if bits <= 8 else np.uint16)
