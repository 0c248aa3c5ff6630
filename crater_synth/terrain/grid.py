"""The crater's local horizontal grid: east-north offsets on the tangent plane to points on the sphere, and
bilinear sampling of a square grid centred on the crater. One copy, used by the terrain patch, the catalogue
check and every later consumer of a crater-centred grid.
"""

from __future__ import annotations

import numpy as np

from crater_core.geometry import MOON_RADIUS_M, enu_basis, latlon_to_mc, mc_to_latlon


def sphere_points(e: np.ndarray, n: np.ndarray, lat: float, lon: float):
    """Unit directions (Moon-centred) and (lat, lon) in degrees of the sphere points below the tangent-plane
    offsets (e, n) metres east and north of (lat, lon): the point on the plane, projected radially."""
    basis = enu_basis(lat, lon)
    p = latlon_to_mc(lat, lon) + np.asarray(e)[..., None] * basis[0] + np.asarray(n)[..., None] * basis[1]
    dirs = p / np.linalg.norm(p, axis=-1, keepdims=True)
    plat, plon, _ = mc_to_latlon(dirs * MOON_RADIUS_M)
    return dirs, plat, plon


def bilinear(grid: np.ndarray, half_width: float, spacing: float, e, n) -> np.ndarray:
    """Bilinear samples of ``grid`` (rows = north, columns = east, cell centres from -half_width to
    +half_width every ``spacing`` metres) at (e, n); clamped to the edge outside."""
    from scipy.ndimage import map_coordinates

    rows = (np.asarray(n, dtype=float) + half_width) / spacing
    cols = (np.asarray(e, dtype=float) + half_width) / spacing
    return map_coordinates(grid, [rows, cols], order=1, mode="nearest")
