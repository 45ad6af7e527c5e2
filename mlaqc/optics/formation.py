"""Sensor-side image formation the geometric tracer leaves out: microlens diffraction, pixel crosstalk
and pixel response non-uniformity (PRNU), applied to the rendered photon image before read-out.

Diffraction is a convolution with the Fraunhofer PSF of one microlens' clear aperture (its cell, square
or hexagonal, or its circle with `mla.aperture = "circle"`, less the corners where its two surfaces
cross, `mla.corners = "opaque"`), seen from the sensor gap, at
the config's wavelength, integrated over the pixel area. For a white image this is exact to the extent
that (1) every lens has the same aperture (a lens' error changes its PSF negligibly), (2) the light is
one wavelength (a real source's bandwidth smooths the PSF's rings), (3) the PSF does not change over a
sub-image (paraxial: the chief-ray tilt at the array's corner, about 6°, widens it by under 1 %), and
(4) the aperture is illuminated uniformly and incoherently (the main lens' pupil is an extended source).
The kernel is cut at `KERNEL_HALF_PX` and renormalized: the sinc² tails beyond it (about 1 % of the
energy) are moved inside instead of lost. Crosstalk moves a fraction of every pixel's charge to each of
its four neighbours (carrier diffusion); PRNU is a fixed per-pixel gain pattern of the sensor, the same
in every frame (its own seed).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from mlaqc.errors import InputError
from mlaqc.optics.config import CameraConfig

KERNEL_HALF_PX = 5  # the diffraction kernel covers ±5 px: beyond 9 zeros of the Table 1 PSF
_SAMPLES_PER_PX = 15  # PSF samples per pixel side before pixel integration (odd: a sample at the centre)
_PUPIL_SAMPLES = 2048  # FFT size of the aperture plane


@dataclass(frozen=True)
class FormationKernels:
    """What `apply_formation` uses: the combined PSF (diffraction * crosstalk) and the PRNU gain map."""

    psf: np.ndarray  # (2K+1, 2K+1), sums to 1
    prnu: np.ndarray | None  # (H, W) gain around 1, or None


def aperture_corner_radius_um(cfg: CameraConfig) -> float:
    """Radius (µm from the lens axis) where the two spherical surfaces cross; inf if they never do."""
    mla = cfg.mla
    if mla.corners == "clear":
        return math.inf
    r1, r2, t = abs(mla.radius_front_um), abs(mla.radius_back_um), mla.thickness_um

    def sag(r: float, rho: float) -> float:  # a flat surface (r = inf) has none
        return 0.0 if math.isinf(r) else r - math.sqrt(max(r * r - rho * rho, 0.0))

    def edge(rho: float) -> float:  # thickness left at radius rho (convex front and back)
        s1 = sag(r1, rho) if mla.radius_front_um > 0 else -sag(r1, rho)
        s2 = sag(r2, rho) if mla.radius_back_um < 0 else -sag(r2, rho)
        return t - s1 - s2

    lo, hi = 0.0, min(r1, r2)
    if edge(hi) > 0:
        return math.inf
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if edge(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def diffraction_psf(cfg: CameraConfig, step_px: float = 1.0) -> np.ndarray:
    """The microlens' diffraction PSF as a convolution kernel for an image sampled every `step_px`
    pixels, summing to 1: the continuous Fraunhofer PSF low-passed to that sampling's Nyquist band
    (the kernel that maps samples of an image to samples of the image convolved with the PSF, for an
    image band-limited to its sampling). At step 1 it acts on a rendered frame; at 1/8 on the
    reference model's 8x finer render."""
    z_um = cfg.layout.sensor_gap_mm * 1e3 + 0.5 * cfg.mla.thickness_um  # aperture (≈ mid-lens) to sensor
    psf, fine_px = _fine_psf(cfg.geometry.wavelength_nm * 1e-3, z_um, cfg.pixel_at_mla_um, cfg.mla.pitch_um,
                             aperture_corner_radius_um(cfg), aperture_shape(cfg), cfg.mla.aperture_diameter_um or 0.0)
    half = int(round(KERNEL_HALF_PX / step_px))
    out = np.arange(-half, half + 1) * step_px
    fine = (np.arange(psf.shape[0]) - psf.shape[0] // 2) * fine_px
    s = np.sinc((out[:, None] - fine[None, :]) / step_px)  # ideal low-pass to the output sampling
    kern = s @ psf @ s.T
    return kern / kern.sum()


def aperture_shape(cfg: CameraConfig) -> str:
    """The microlens' aperture outline: 'square' or 'hex' (its cell, 100 % fill) or 'circle'."""
    return "circle" if cfg.mla.aperture == "circle" else cfg.mla.packing


def aperture_mask(x_um: np.ndarray, y_um: np.ndarray, shape: str, pitch_um: float, diameter_um: float,
                  corner_um: float) -> np.ndarray:
    """True inside the aperture centred on the lens axis: the square cell, the pointy-top hexagonal cell
    (flat sides at x = ±p/2 facing the row neighbours, mlaqc.optics.lattice) or the circle of
    `diameter_um`, less the corners beyond `corner_um`."""
    half = 0.5 * pitch_um
    if shape == "circle":
        inside = x_um * x_um + y_um * y_um <= (0.5 * diameter_um) ** 2
    elif shape == "hex":
        s = math.sqrt(3.0) / 2.0
        inside = ((np.abs(x_um) <= half) & (np.abs(0.5 * x_um + s * y_um) <= half)
                  & (np.abs(0.5 * x_um - s * y_um) <= half))
    else:
        inside = (np.abs(x_um) <= half) & (np.abs(y_um) <= half)
    return inside & (x_um * x_um + y_um * y_um <= corner_um ** 2)


@functools.lru_cache(maxsize=8)
def _fine_psf(wavelength_um: float, z_um: float, pixel_um: float, pitch_um: float,
              corner_um: float, shape: str = "square", diameter_um: float = 0.0) -> tuple[np.ndarray, float]:
    """The Fraunhofer PSF (intensity, summing to 1) by FFT of the aperture, sampled every 1/15 px over
    ±(KERNEL_HALF_PX + 1) px, and that step in px. An N-point FFT over a pupil window W samples the sensor
    plane every λ z / W: W is chosen to give `_SAMPLES_PER_PX` samples per pixel."""
    window_um = wavelength_um * z_um * _SAMPLES_PER_PX / pixel_um
    step_um = window_um / _PUPIL_SAMPLES
    if pitch_um > 0.5 * window_um or pitch_um < 16 * step_um:
        raise InputError("cannot model this microlens' diffraction: its aperture does not fit the sampling "
                         "(switch formation.diffraction off)")
    coords = (np.arange(_PUPIL_SAMPLES) - _PUPIL_SAMPLES // 2) * step_um
    x, y = np.meshgrid(coords, coords)
    aperture = aperture_mask(x, y, shape, pitch_um, diameter_um, corner_um)
    field = np.fft.fftshift(np.fft.fft2(np.fft.ifftshift(aperture.astype(np.float64))))
    intensity = np.abs(field) ** 2
    c, reach = _PUPIL_SAMPLES // 2, (KERNEL_HALF_PX + 1) * _SAMPLES_PER_PX
    crop = intensity[c - reach: c + reach + 1, c - reach: c + reach + 1]
    return crop / crop.sum(), 1.0 / _SAMPLES_PER_PX


def crosstalk_kernel(fraction: float) -> np.ndarray:
    """3 x 3 kernel moving `fraction` of a pixel's charge to each of its four neighbours."""
    kern = np.zeros((3, 3))
    kern[1, 1] = 1.0 - 4.0 * fraction
    kern[0, 1] = kern[2, 1] = kern[1, 0] = kern[1, 2] = fraction
    return kern


def blur_key(cfg: CameraConfig) -> dict:
    """What of `cfg.formation` shapes a healthy sub-image (for the models' content keys): {} when the
    formation adds no blur, so models rendered without it keep their keys."""
    f = cfg.formation
    if not f.diffraction and f.crosstalk == 0:
        return {}
    return {"formation": {"diffraction": f.diffraction, "crosstalk": f.crosstalk}}


def formation_kernels(cfg: CameraConfig, shape: tuple[int, int], with_prnu: bool = True) -> FormationKernels:
    """The kernels of `cfg.formation` for a frame of `shape` (`with_prnu`: False leaves the PRNU out)."""
    f = cfg.formation
    psf = diffraction_psf(cfg) if f.diffraction else np.ones((1, 1))
    if f.crosstalk > 0:
        psf = cv2.filter2D(np.pad(psf, 1), -1, crosstalk_kernel(f.crosstalk), borderType=cv2.BORDER_CONSTANT)
    gain = None
    if with_prnu and f.prnu_rms > 0:
        gain = 1.0 + np.random.default_rng(f.prnu_seed).normal(0.0, f.prnu_rms, shape)
    return FormationKernels(psf / psf.sum(), gain)


def apply_formation(photons: np.ndarray, cfg: CameraConfig, kernels: FormationKernels | None = None) -> np.ndarray:
    """Expected photons after diffraction, crosstalk and PRNU (a new float64 array; energy kept except at
    the frame's border, where light leaving the sensor is lost, as in the camera)."""
    kernels = kernels or formation_kernels(cfg, photons.shape)
    out = np.asarray(photons, dtype=np.float64)
    if kernels.psf.shape != (1, 1):
        out = cv2.filter2D(out, -1, kernels.psf[::-1, ::-1], borderType=cv2.BORDER_CONSTANT)
        np.maximum(out, 0.0, out=out)  # a DFT-based filter leaves round-off below zero where there is no light
    if kernels.prnu is not None:
        out = out * kernels.prnu
    return out
