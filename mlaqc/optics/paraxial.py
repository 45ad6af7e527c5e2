"""Paraxial (first-order) optics of thick spherical lenses: the independent yardstick for the tracer.

Sign convention: light travels +z; a radius is positive when its centre lies after its vertex.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ThickLens:
    """First-order properties of a thick lens in air, all lengths in the caller's unit."""

    efl: float  # effective focal length
    bfd: float  # back focal distance, from the rear vertex
    ffd: float  # front focal distance, from the front vertex (positive = in front)
    front_principal: float  # front principal plane, measured from the front vertex (+ = inside)
    rear_principal: float  # rear principal plane, measured from the rear vertex (+ = inside)


def thick_lens(radius_front: float, radius_back: float, thickness: float, n: float) -> ThickLens:
    """Lensmaker's equation for a thick lens and its principal planes (Hecht, Optics §6.1); scalars or
    arrays (a flat surface is an infinite radius: 1 / inf = 0)."""
    c1, c2 = 1.0 / radius_front, 1.0 / radius_back
    power = (n - 1.0) * (c1 - c2 + (n - 1.0) * thickness * c1 * c2 / n)
    efl = 1.0 / power
    p1 = (n - 1.0) * c1
    p2 = -(n - 1.0) * c2
    rear_principal = efl * p1 * thickness / n  # H' lies this far before the rear vertex
    front_principal = efl * p2 * thickness / n  # H lies this far after the front vertex
    return ThickLens(
        efl=efl,
        bfd=efl - rear_principal,
        ffd=efl - front_principal,
        front_principal=front_principal,
        rear_principal=rear_principal,
    )


def image_distance(focal: float, object_distance: float) -> float:
    """Gaussian imaging: image distance after H' for an object `object_distance` before H (both > 0)."""
    return 1.0 / (1.0 / focal - 1.0 / object_distance)


def subimage_pitch(pitch: float, pupil_distance: float, lens_to_sensor: float) -> float:
    """Spacing of white-image sub-image centres: p*(b+f)/b, the chief rays from the pupil centre."""
    return pitch * (pupil_distance + lens_to_sensor) / pupil_distance
