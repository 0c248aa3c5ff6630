"""Terrain meshes (near and far field) from the terrain npz grids, built with ``foreach_set``.

A grid ``xyz`` of shape (rows, cols, 3) (ENU metres, curvature included) becomes one quad per grid
cell, smooth shaded (interpolated vertex normals). The winding is chosen so that the face normals
point up (+z) whatever the row/column orientation of the grid. The near mesh gets a UV map of
normalised grid coordinates (u = col / (cols - 1), v = row / (rows - 1)).
"""

from __future__ import annotations

import bpy
import numpy as np

from blender_gen import compat


def _quads(rows: int, cols: int, keep: np.ndarray | None) -> np.ndarray:
    idx = np.arange(rows * cols, dtype=np.int64).reshape(rows, cols)
    q = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1)
    if keep is not None:
        q = q[keep]
    return q.reshape(-1, 4)


def _orient_up(q: np.ndarray, verts: np.ndarray, sample: int = 20000) -> np.ndarray:
    """Reverse the winding if the quads' summed (area-weighted) normal points down. Every quad of a grid
    has the same winding, so an even sample of ``sample`` quads decides (a tenth of the scene build of a
    10^6-quad patch when all were summed)."""
    a, b, c, d = (verts[q[:: max(1, len(q) // sample), k]] for k in range(4))
    n = np.cross(c - a, d - b)  # quad normal (diagonals' cross product), length = 2 * area
    if n[:, 2].sum() < 0.0:
        q = q[:, ::-1]
    return q


def build_grid_mesh(
    name: str, xyz: np.ndarray, keep_quads: np.ndarray | None = None, grid_uv: bool = False, collection=None
) -> bpy.types.Object:
    """Mesh object with one smooth-shaded quad per kept grid cell (unused vertices dropped)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    rows, cols = xyz.shape[:2]
    verts = xyz.reshape(-1, 3)
    q = _quads(rows, cols, None if keep_quads is None else np.asarray(keep_quads, dtype=bool))
    if len(q) == 0:
        raise ValueError(f"mesh {name!r}: no quads")
    q = _orient_up(q, verts)

    used = np.unique(q) if keep_quads is not None else None  # all quads kept: every vertex is used
    if used is not None and len(used) < len(verts):  # compact: drop vertices no kept quad uses
        remap = np.full(len(verts), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        uv_src = used
        verts = verts[used]
        q = remap[q]
    else:
        uv_src = np.arange(len(verts))

    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts))
    me.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    me.loops.add(q.size)
    me.loops.foreach_set("vertex_index", q.astype(np.int32).ravel())
    me.polygons.add(len(q))
    compat.set_polygon_loops(me, np.arange(0, q.size, 4, dtype=np.int32), np.full(len(q), 4, dtype=np.int32))
    if not me.polygons[0].use_smooth:  # Blender >= 4.1 makes new faces smooth (no sharp_face attribute)
        me.polygons.foreach_set("use_smooth", np.ones(len(q), dtype=bool))
    if grid_uv:
        r, c = np.divmod(uv_src, cols)
        uv_vert = np.stack([c / max(cols - 1, 1), r / max(rows - 1, 1)], axis=-1).astype(np.float32)
        layer = me.uv_layers.new(name="grid")
        layer.data.foreach_set("uv", uv_vert[q.ravel()].ravel())
    me.update(calc_edges=True)

    obj = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj


def load_terrain_meshes(terrain: dict, mat: bpy.types.Material) -> list[bpy.types.Object]:
    """Near (and, when present, far) mesh objects with ``mat`` assigned."""
    objs = [build_grid_mesh("near", terrain["near_xyz"], grid_uv=True)]
    far = terrain.get("far_xyz")
    if far is not None and far.size and far.shape[0] > 1 and far.shape[1] > 1:
        keep = terrain.get("far_keep_quads")
        if keep is None or keep.any():
            objs.append(build_grid_mesh("far", far, keep))
    for obj in objs:
        obj.data.materials.append(mat)
    return objs
