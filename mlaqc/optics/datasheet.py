"""Optics from datasheet numbers: an ideal main lens (image-side f-number, or objective magnification, NA
and tube lens), an MLA sold by focal length and profile, and a relay between the MLA's focal plane and the
sensor, turned into the quantities the tracer and the inspection use (DESIGN.md §2c).

A light-field microscope's objective and tube lens are an aplanatic imaging system, telecentric on the
image side: its image-side working f-number is M / (2 NA) and every sub-image sits straight behind its
lens. A camera lens is given by its f-number and the distance of its exit pupil from the MLA. Neither is
traced through surfaces: the tracer draws image-side rays from the exit pupil disc (a plane disc: the
paraxial ideal system; for f/2.5 the edge rays' sin and tan differ by 2 %) and the main lens passes them
unchanged. A relay of magnification m images the MLA's focal plane onto the sensor: the model sees a sensor
of pixel/m at that plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# An image-side telecentric main lens (exit pupil at infinity) is traced with its exit pupil this far from
# the MLA: the sub-image pitch then differs from the lens pitch by f/d (3 ppm for a 3 mm microlens).
TELECENTRIC_PUPIL_MM = 1.0e6
# the tube lens an objective's magnification is quoted for (Nikon, Leica, Mitutoyo, Thorlabs; Olympus 180,
# Zeiss 165: set main_lens.design_tube_lens_mm)
DEFAULT_TUBE_LENS_MM = 200.0
PROFILES = ("plano-convex", "biconvex")
# f-number and NA given together must agree to this (relative): datasheets round to 2-3 figures
F_NUMBER_AGREEMENT = 0.02


@dataclass(frozen=True)
class Objective:
    """An infinity-corrected objective with its tube lens, reduced to what the MLA sees."""

    magnification: float  # as used: the datasheet's, scaled by the tube lens in use over the design one
    na_image: float  # image-side numerical aperture NA / M
    f_number: float  # image-side working f-number 1 / (2 NA_image)


def objective(magnification: float, na: float, tube_lens_mm: float | None,
              design_tube_lens_mm: float | None) -> Objective:
    """Magnification and image-side f-number of objective + tube lens (Abbe sine condition: the working
    f-number of an aplanatic system is 1 / (2 n' sin u'), n' = 1 behind the tube lens)."""
    design = design_tube_lens_mm or DEFAULT_TUBE_LENS_MM
    m = magnification * (tube_lens_mm or design) / design
    na_image = na / m
    return Objective(m, na_image, 1.0 / (2.0 * na_image))


def mla_radii_um(focal_length_um: float, n: float, thickness_um: float, profile: str) -> tuple[float, float]:
    """(front, back) radii (µm, optical sign convention) of a microlens of effective focal length f.

    Plano-convex (convex side towards the main lens, flat back): R = f (n - 1), exact whatever the
    thickness (a flat surface has no power). Symmetric biconvex (R, -R) of vertex thickness t: the thick
    lens' 1/f = (n-1) (2/R - (n-1) t / (n R^2)) solved for R, R = f (n-1) (1 + sqrt(1 - t / (n f))); no
    real root when t > n f."""
    if profile == "plano-convex":
        return focal_length_um * (n - 1.0), math.inf
    disc = 1.0 - thickness_um / (n * focal_length_um)
    if disc < 0.0:
        raise ValueError(f"a symmetric biconvex lens {thickness_um} µm thick cannot have a focal length of "
                         f"{focal_length_um} µm (at most t/n)")
    r = focal_length_um * (n - 1.0) * (1.0 + math.sqrt(disc))
    return r, -r


def telecentric(exit_pupil_mm: float | None) -> bool:
    """An exit pupil at infinity (None counts as telecentric: the objective form's default)."""
    return exit_pupil_mm is None or math.isinf(exit_pupil_mm)


def traced_pupil_mm(exit_pupil_mm: float | None) -> float:
    """Distance of the exit pupil from the MLA that the tracer uses (TELECENTRIC_PUPIL_MM for infinity)."""
    return TELECENTRIC_PUPIL_MM if telecentric(exit_pupil_mm) else float(exit_pupil_mm)


def pupil_radius_mm(distance_mm: float, f_number: float) -> float:
    """Radius of an exit pupil `distance_mm` from the image whose marginal ray has sin u' = 1 / (2N)."""
    sin_u = 1.0 / (2.0 * f_number)
    return distance_mm * sin_u / math.sqrt(1.0 - sin_u * sin_u)


def derived_numbers(cfg) -> list[tuple[str, str]]:
    """What a user checks against the instrument before trusting a verdict: (label, value) rows."""
    ml, mla, lay = cfg.main_lens, cfg.mla, cfg.layout
    rows: list[tuple[str, str]] = []
    if ml.ideal:
        if ml.na is not None:
            obj = objective(ml.magnification, ml.na, ml.tube_lens_mm, ml.design_tube_lens_mm)
            rows.append(("objective", f"{ml.magnification:g}x / NA {ml.na:g}, tube lens "
                                      f"{ml.tube_lens_mm or ml.design_tube_lens_mm or DEFAULT_TUBE_LENS_MM:g} mm: "
                                      f"magnification {obj.magnification:.4g}, image-side NA {obj.na_image:.4g}"))
        rows.append(("main lens image-side f-number", f"f/{ml.f_number:.4g}"))
        rows.append(("exit pupil", "at infinity (image-side telecentric)" if telecentric(ml.exit_pupil_mm)
                     else f"{ml.exit_pupil_mm:g} mm before the MLA"))
        d = cfg.geometry.image_defocus_mm or 0.0
        sample = ""
        if ml.na is not None:  # axial magnification M^2 n' / n, n' = 1 behind the tube lens
            m = objective(ml.magnification, ml.na, ml.tube_lens_mm, ml.design_tube_lens_mm).magnification
            sample = f"; the sample plane {d / m ** 2 * 1e3:.4g} µm × n (immersion index) from focus"
        rows.append(("scene's image", f"{d:g} mm before the MLA's mid-plane (geometry.image_defocus_mm){sample}"))
    else:
        rows.append(("main lens (thick)", f"EFL {lay.main.efl:.4f} mm, f/{lay.main.efl / ml.diameter_mm:.4g} at infinity, "
                                          f"MLA {lay.mla_distance_mm:.3f} mm behind its rear vertex, object "
                                          f"{lay.object_distance_mm:.3f} mm before its front vertex"))
    if mla.focal_length_um is not None:
        back = "flat" if math.isinf(mla.radius_back_um) else f"{mla.radius_back_um:.2f} µm"
        rows.append(("microlens radii (derived)", f"front {mla.radius_front_um:.2f} µm, back {back} "
                                                  f"({mla.profile}, n {mla.refractive_index:g})"))
    rows.append(("microlens focal length", f"{lay.micro.efl * 1e3:.2f} µm (back focal distance "
                                           f"{lay.micro.bfd * 1e3:.2f} µm)"))
    rows.append(("matched f-number", f"f/{lay.micro.efl * 1e3 / mla.pitch_um:.4g} (microlens focal length / pitch); "
                                     f"the main lens' image-side working f-number f/{lay.image_f_number:.4g}"))
    rows.append(("sensor gap", f"{lay.sensor_gap_mm * 1e3:.2f} µm behind the MLA's rear vertex"
                               + (" (the relay's object plane)" if cfg.relay.present else "")))
    if cfg.relay.present:
        rows.append(("relay", f"magnification {cfg.relay.magnification:g}: {cfg.sensor.pixel_um:g} µm pixels see "
                              f"{cfg.pixel_at_mla_um:.4g} µm of the MLA's focal plane"))
    rows.append(("sub-image pitch", f"{lay.subimage_pitch_px:.4f} px (lens pitch {mla.pitch_um:g} µm over "
                                    f"{cfg.pixel_at_mla_um:.4g} µm"
                                    + (" exactly: telecentric)" if ml.ideal and telecentric(ml.exit_pupil_mm)
                                       else f", times (b + gap) / b, b = {lay.pupil_to_mla_mm:.2f} mm)")))
    return rows
