"""A procedural crater field (:mod:`crater_core.procedural`) as the Blender worker's terrain patch.

The grid is placed on the Moon as the DEM patches are (:mod:`crater_synth.terrain.patch`): grid point
(x, y) sits on the tangent plane at (lat, lon) at e = x - centre, n = y - centre, is projected radially
onto the 1737.4 km sphere and raised by its height, and is expressed in the ENU frame of (lat, lon). The
patch (:func:`patch_arrays`) and the labels projected from the crater table (``crater-synth
detection-frames``) use the same mapping, :func:`grid_to_enu`. Near field only: no far field.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from crater_core.geometry import MOON_RADIUS_M, enu_basis, mc_to_enu
from crater_core.procedural import ProceduralTerrain
from crater_core.schema import atomic_write_bytes
from crater_synth.terrain.grid import sphere_points


def grid_centre_m(terrain: ProceduralTerrain) -> float:
    """The grid's centre coordinate (x = y), metres: the patch origin lies below it."""
    return 0.5 * (terrain.height.shape[0] - 1) * terrain.spacing_m


def grid_to_enu(terrain: ProceduralTerrain, x_m, y_m, height_m, lat: float, lon: float):
    """(ENU points (..., 3), local up unit vectors (..., 3)) of grid coordinates (x, y) raised by
    ``height_m``, in the patch frame of (lat, lon)."""
    c = grid_centre_m(terrain)
    dirs, _, _ = sphere_points(np.asarray(x_m, dtype=float) - c, np.asarray(y_m, dtype=float) - c, lat, lon)
    radius = MOON_RADIUS_M + np.asarray(height_m, dtype=float)
    points = mc_to_enu(dirs * radius[..., None], lat, lon)
    return points, dirs @ enu_basis(lat, lon).T


def height_at(terrain: ProceduralTerrain, x_m, y_m) -> np.ndarray:
    """Bilinear samples of the grid's height at (x, y) metres (clamped to the edge outside)."""
    from scipy.ndimage import map_coordinates

    s = terrain.spacing_m
    rows, cols = np.broadcast_arrays(np.asarray(y_m, dtype=float) / s, np.asarray(x_m, dtype=float) / s)
    samples = map_coordinates(terrain.height, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
    return samples.reshape(rows.shape)


def patch_arrays(terrain: ProceduralTerrain, lat: float, lon: float) -> dict[str, np.ndarray]:
    """The worker's terrain arrays (blender_gen/job.py ``load_terrain``) of the grid centred on (lat, lon):
    rows ascending north, columns east, as crater_synth/terrain/patch.py builds them. No far field."""
    n = terrain.height.shape[0]
    coords = np.arange(n) * terrain.spacing_m
    xx, yy = np.meshgrid(coords, coords)
    xyz, _ = grid_to_enu(terrain, xx, yy, terrain.height, lat, lon)
    return {
        "near_xyz": xyz.astype(np.float32),
        "far_xyz": np.zeros((0, 0, 3), np.float32),
        "far_keep_quads": np.zeros((0, 0), bool),
        "near_height": terrain.height.astype(np.float32),
    }


def write_patch(terrain: ProceduralTerrain, lat: float, lon: float, path: Path) -> None:
    """:func:`patch_arrays` as an ``.npz`` at ``path``, written atomically."""
    buf = io.BytesIO()
    np.savez(buf, **patch_arrays(terrain, lat, lon))
    atomic_write_bytes(path, buf.getvalue())
