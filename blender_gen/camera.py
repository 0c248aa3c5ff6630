"""Cameras: the 90-degree perspective view camera (pose from ``geometry.look_at_camera``, border/crop
render of a full-frame pixel box) and the orthographic top-down camera of the fast path's maps.
"""

from __future__ import annotations

import math

import bpy
import mathutils
import numpy as np

from blender_gen import border
from crater_core import geometry


def create_camera(scene, name: str = "view") -> bpy.types.Object:
    data = bpy.data.cameras.new(name)
    data.type = "PERSP"
    data.sensor_fit = "AUTO"
    data.lens_unit = "FOV"
    data.shift_x = data.shift_y = 0.0
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    return obj


def pose_matrix(rotation: np.ndarray, position: np.ndarray) -> mathutils.Matrix:
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = position
    return mathutils.Matrix(m.tolist())


def _set(owner, attr: str, value) -> None:
    """Assign only on change: each write tags a Cycles re-sync (re-assigning ``scene.camera``, even
    to the same object, costs ~0.2 s per render; measured in docs/renderer.md)."""
    if getattr(owner, attr) != value:
        setattr(owner, attr, value)


def _set_fraction(owner, attr: str, value: float) -> None:
    """:func:`_set` for a float32 property (the stored value is the float32 rounding of ``value``)."""
    if abs(getattr(owner, attr) - value) > 1e-7:
        setattr(owner, attr, value)


def full_frame_crop(crop, frame_width: int) -> tuple[int, int, int, int]:
    u0, v0, u1, v1 = (int(c) for c in crop)
    if not (0 <= u0 < u1 <= frame_width and 0 <= v0 < v1 <= frame_width):
        raise ValueError(f"crop {list(crop)} is not a non-empty box inside the {frame_width}-px frame")
    return u0, v0, u1, v1


def set_view(scene, cam_obj, pose: geometry.CameraPose, frame_width: int, crop) -> None:
    """Aim ``cam_obj`` (``pose``) and render only the ``crop`` box (u right, v down, top-left origin,
    exclusive max) of the square ``frame_width`` frame, keeping the full frame's geometry."""
    u0, v0, u1, v1 = full_frame_crop(crop, frame_width)
    cam = cam_obj.data
    _set(cam, "type", "PERSP")
    _set(cam, "angle", math.radians(pose.fov_deg))
    rng = float(np.linalg.norm(pose.position))
    _set(cam, "clip_start", max(1e-3 * rng, 0.01))
    _set(cam, "clip_end", 1e8)
    m = pose_matrix(pose.rotation, pose.position)
    if cam_obj.matrix_world != m:
        cam_obj.matrix_world = m
    _set(scene, "camera", cam_obj)
    r = scene.render
    _set(r, "resolution_x", int(frame_width))
    _set(r, "resolution_y", int(frame_width))
    _set(r, "use_border", True)
    _set(r, "use_crop_to_border", True)
    # Fractions strictly inside the edge pixels: Blender truncates float32 border * width back to
    # pixels, and an exact u0 / W can come back as u0 - 1 (blender_gen/border.py).
    min_x, max_x, min_y, max_y = border.border_fractions((u0, v0, u1, v1), frame_width)
    _set_fraction(r, "border_min_x", min_x)
    _set_fraction(r, "border_max_x", max_x)
    _set_fraction(r, "border_min_y", min_y)
    _set_fraction(r, "border_max_y", max_y)


def set_top_down(scene, cam_obj, half_width_m: float, pixels: int, z_top_m: float) -> None:
    """Orthographic camera looking straight down (-z) on the square [-hw, hw]^2 (ENU x right = east,
    image up = +y north). Pixel (col, row) of the ``pixels``^2 image covers x in
    [-hw + col*d, -hw + (col+1)*d], y in [hw - (row+1)*d, hw - row*d] with d = 2 hw / pixels."""
    cam = cam_obj.data
    _set(cam, "type", "ORTHO")
    _set(cam, "ortho_scale", 2.0 * half_width_m)
    _set(cam, "clip_start", 1.0)
    _set(cam, "clip_end", 1e8)
    m = pose_matrix(np.eye(3), np.array([0.0, 0.0, z_top_m]))
    if cam_obj.matrix_world != m:
        cam_obj.matrix_world = m
    _set(scene, "camera", cam_obj)
    r = scene.render
    _set(r, "resolution_x", int(pixels))
    _set(r, "resolution_y", int(pixels))
    _set(r, "use_border", False)
    _set(r, "use_crop_to_border", False)
