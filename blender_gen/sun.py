"""The Sun: a Cycles sun lamp (parallel rays, finite angular diameter) calibrated to give I/F.

Cycles' sun strength is an irradiance: a white Lambertian surface lit at incidence cosine mu0 by a
sun of strength S renders S * mu0 / pi (measured: strength 1, mu0 = 0.866 -> 0.2757, see
docs/renderer.md and tests/test_render_physics.py). The radiance factor is I/F = pi * L / J for
solar irradiance J, so strength ``pi`` makes the rendered value equal I/F for a unit-irradiance Sun
(a white Lambertian surface facing the Sun renders 1).
"""

from __future__ import annotations

import math

import bpy
import mathutils
import numpy as np

from crater_core import geometry

SUN_STRENGTH = math.pi


def create_sun(scene) -> bpy.types.Object:
    data = bpy.data.lights.new("sun", "SUN")
    data.energy = SUN_STRENGTH
    data.angle = math.radians(geometry.SUN_ANGULAR_DIAMETER_DEG)
    data.color = (1.0, 1.0, 1.0)
    data.use_shadow = True
    # Only direct light on surfaces matters; keep the sun out of camera/glossy rays.
    for attr in ("diffuse_factor", "specular_factor", "volume_factor"):
        if hasattr(data, attr):
            setattr(data, attr, 1.0 if attr == "diffuse_factor" else 0.0)
    obj = bpy.data.objects.new("sun", data)
    scene.collection.objects.link(obj)
    return obj


def to_sun_vector(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit ENU vector from the scene towards the Sun."""
    return geometry.direction_from_elevation_azimuth(elevation_deg, azimuth_deg)


def aim_sun(sun_obj, to_sun) -> None:
    """Point the lamp so its rays travel along -to_sun (a Blender sun shines along its local -Z)."""
    v = mathutils.Vector([float(x) for x in to_sun]).normalized()
    sun_obj.rotation_mode = "QUATERNION"
    sun_obj.rotation_quaternion = v.to_track_quat("Z", "Y")


def set_enabled(sun_obj, on: bool) -> None:
    """Strength 0 removes the lamp from Cycles' light sampling (used for G-buffer renders)."""
    energy = SUN_STRENGTH if on else 0.0
    if sun_obj.data.energy != energy:  # unchanged: no write, no Cycles light re-sync
        sun_obj.data.energy = energy
