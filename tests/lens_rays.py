"""Exact rays through a thick spherical main lens, written apart from mlaqc's tracer (Snell's law in vector
form at two spheres): where a point source's light crosses a plane behind the lens, as a function of the
point it passed in another plane (the pupil plane a plenoptic view selects). Used to check decoded views
against the optics, main lens' spherical aberration included.

Coordinates: z along the axis, the lens' front vertex at z = 0, light along +z; x, y as the tracer's
(lens U(m,n) columns along +x, rows along +y)."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import LinearNDInterpolator


def _refract(d: np.ndarray, normal: np.ndarray, n1: float, n2: float) -> np.ndarray:
    """Unit directions d refracted at unit normals (either orientation) from index n1 into n2."""
    normal = np.where(np.sum(d * normal, axis=1, keepdims=True) > 0, -normal, normal)  # face the light
    eta = n1 / n2
    cos_i = -np.sum(d * normal, axis=1, keepdims=True)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    return eta * d + (eta * cos_i - np.sqrt(np.maximum(k, 0.0))) * normal


def _hit_sphere(p: np.ndarray, d: np.ndarray, vertex_z: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Points where rays p + t d meet the sphere of `radius` whose vertex is at z = vertex_z (centre at
    vertex_z + radius), the intersection nearest the vertex; and the unit normals there."""
    c = np.array([0.0, 0.0, vertex_z + radius])
    oc = p - c
    b = np.sum(oc * d, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - radius * radius)
    root = np.sqrt(np.maximum(disc, 0.0))
    t = np.where(radius > 0, -b - root, -b + root)
    hit = p + t[:, None] * d
    return hit, (hit - c) / abs(radius)


def point_source_map(obj_xy_mm: tuple[float, float], obj_z_mm: float, *, radius_front_mm: float,
                     radius_back_mm: float, thickness_mm: float, index: float, diameter_mm: float,
                     pupil_z_mm: float, target_z_mm: float, rays: int = 201):
    """A function P(x, y) -> (x, y) at target_z_mm: where the ray from the object point (at z = obj_z_mm,
    negative) that crosses the plane pupil_z_mm at P meets the plane target_z_mm; NaN outside the beam."""
    g = np.linspace(-0.5 * diameter_mm, 0.5 * diameter_mm, rays)
    gx, gy = np.meshgrid(g, g)
    keep = gx * gx + gy * gy <= (0.5 * diameter_mm) ** 2
    aim = np.stack([gx[keep], gy[keep], np.zeros(keep.sum())], axis=1)  # aimed at the front vertex plane
    start = np.tile(np.array([obj_xy_mm[0], obj_xy_mm[1], obj_z_mm]), (aim.shape[0], 1))
    d = aim - start
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p1, n1 = _hit_sphere(start, d, 0.0, radius_front_mm)
    d1 = _refract(d, n1, 1.0, index)
    p2, n2 = _hit_sphere(p1, d1, thickness_mm, radius_back_mm)
    d2 = _refract(d1, n2, index, 1.0)
    inside = np.hypot(p2[:, 0], p2[:, 1]) <= 0.5 * diameter_mm
    p2, d2 = p2[inside], d2[inside]
    at = lambda z: p2[:, :2] + ((z - p2[:, 2]) / d2[:, 2])[:, None] * d2[:, :2]  # noqa: E731
    return LinearNDInterpolator(at(pupil_z_mm), at(target_z_mm))


def views_against_rays(lf, radius_px: float, cfg, scene_cfg, obj_xy_mm: tuple[float, float]):
    """(decoded, exact): for every view inside 0.8 of the pupil's image radius `radius_px`, the centroid in
    lenses (s, t) of a point source's light in that view of the light field `lf` (mlaqc.decode), and where the
    exact ray from the point through that view's pupil point meets the MLA, in the same units. `scene_cfg` is
    the camera as rendered (its object plane), `cfg` the one decoded."""
    lay, ml = scene_cfg.layout, cfg.main_lens
    rays = point_source_map(obj_xy_mm, -lay.object_distance_mm, radius_front_mm=ml.radius_front_mm,
                            radius_back_mm=ml.radius_back_mm, thickness_mm=ml.thickness_mm, index=ml.refractive_index,
                            diameter_mm=ml.diameter_mm, pupil_z_mm=lay.z_mla_mm - lay.pupil_to_mla_mm,
                            target_z_mm=lay.z_mla_mm)
    pupil_per_px = cfg.sensor.pixel_um * 1e-3 * lay.pupil_to_mla_mm / (lay.z_sensor_mm - lay.z_mla_mm)
    pitch_mm, centre = cfg.mla.pitch_um * 1e-3, (cfg.mla.count_w - 1) / 2
    t, s = np.mgrid[0:cfg.mla.count_h, 0:cfg.mla.count_w]
    got, want = [], []
    for j, v in enumerate(lf.view_offsets_px):
        for i, u in enumerate(lf.view_offsets_px):
            w = lf.values[j, i] * (lf.weights[j, i] > 0.3)
            if np.hypot(u, v) > 0.8 * radius_px or w.sum() <= 0:
                continue
            got.append(((w * s).sum() / w.sum(), (w * t).sum() / w.sum()))
            # the sub-image inverts the pupil: the view u px right looks through the pupil point u px left
            want.append(rays(np.array([[-u * pupil_per_px, -v * pupil_per_px]]))[0] / pitch_mm + centre)
    return np.array(got), np.array(want)
