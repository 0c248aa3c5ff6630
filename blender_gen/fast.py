"""Fast (production) mode: the sweep's sun x camera factorisation (docs/specification.md, "Performance model").

Per sun azimuth (once per terrain, shared by every worker through an on-disk cache):
    a *horizon map* (crater_core.horizon): the elevation of the terrain's horizon towards the sun
    azimuth at every texel of nested squares (``shadow_map_levels``, the outer one |x|, |y| <=
    shadow_map_extent_factor x D, each ``shadow_map_px``^2), over the near and far field, with the
    Moon's curvature. Every sun elevation of that azimuth reads the same map: the lit fraction is the
    visible part of the solar disc above the horizon (penumbra included), no render needed.
Per camera pose (cached in-process, LRU; the host sends renders camera-major):
    a *G-buffer*: a Cycles render of the crop with the material in "gbuffer" mode (sun off), giving
    the pixel-averaged shading normal, the mean surface point P (AOV) and terrain coverage (AOV),
    and depth. From them: view vectors v = unit(camera - P), mu = N.v, and the bilinear lookup of P's
    (x, y) into the map texels (same for every sun, so indices/weights are cached).
Per render (numpy only):
    I/F = cov * hapke.radiance_factor(mu0 = N.s, mu, cos g = v.s) * disc_fraction(theta - h(P.xy))
with the numpy backend of the same formula the shader nodes are generated from.

Differences from direct mode (docs/renderer.md quantifies them): the Hapke term is evaluated once per
pixel at the mean normal instead of per sample (matters only where a pixel straddles a crease or an
occluding edge); shadows are cast by a Catmull-Rom surface through the mesh vertices instead of the
triangulated mesh (no facet saw-tooth), and the disc fraction is area-weighted, not cosine-weighted
(they differ only within a solar radius of the terminator). Direct light only: ``max_bounces`` is
forced to 0 here.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections import OrderedDict

import numpy as np

from blender_gen import direct
from blender_gen.job import load_terrain
from crater_core import hapke, horizon, horizon_cache


class Float32Ops(hapke.NumpyOps):
    """The numpy backend of ``hapke.radiance_factor`` kept in float32 (about twice as fast as the
    float64 oracle; relative differences ~1e-6, far below the Monte-Carlo noise of the reference)."""

    @staticmethod
    def less_equal(a, b):
        return (np.asarray(a) <= np.asarray(b)).astype(np.float32)


def radiance_factor32(mu0: np.ndarray, mu: np.ndarray, cos_g: np.ndarray, params) -> np.ndarray:
    """I/F of the one Hapke formula (crater_core.hapke) in float32, for mu0 > 0 and mu > 0."""
    return hapke.radiance_factor(
        mu0.astype(np.float32), mu.astype(np.float32), cos_g.astype(np.float32), params, Float32Ops
    ).astype(np.float32)


class FallbackNeeded(Exception):
    """The crop sees terrain outside the horizon map: render this image in direct mode instead."""


class MapGeometry:
    """Nested square map levels, all ``px`` x ``px`` texels, centred on the crater: level k
    has half-width ``half / 2**(levels-1-k)`` (level 0 is the finest). Level texels are stored one
    after the other in one flat array. A point uses the finest level whose square holds its bilinear
    stencil; camera pixels far from the crater are seen obliquely, so their ground footprint grows
    as fast as the coarser levels' texels (docs/renderer.md)."""

    def __init__(self, half_width_m: float, px: int, levels: int):
        self.px = int(px)
        self.halves = [float(half_width_m) / 2 ** (levels - 1 - k) for k in range(levels)]
        self.offsets = [k * self.px * self.px for k in range(levels)]

    def locate(self, x: np.ndarray, y: np.ndarray, valid: np.ndarray):
        """(flat index of the stencil's top-left texel, fx, fy, number of valid points outside)."""
        px = self.px
        i00 = np.zeros(x.shape, dtype=np.int64)
        fx = np.zeros(x.shape, dtype=np.float32)
        fy = np.zeros(x.shape, dtype=np.float32)
        todo = valid.copy()
        for k, (half, off) in enumerate(zip(self.halves, self.offsets)):
            d = 2.0 * half / px
            col = (x + half) / d - 0.5  # texel centres at -hw + (k + 0.5) d
            row = (half - y) / d - 0.5
            last = k == len(self.halves) - 1
            inner = (col >= 0.0) & (col <= px - 1.000001) & (row >= 0.0) & (row <= px - 1.000001)
            take = todo & (inner | last)
            col = np.clip(col[take], 0.0, px - 1.000001)
            row = np.clip(row[take], 0.0, px - 1.000001)
            c0 = np.floor(col)
            r0 = np.floor(row)
            i00[take] = off + r0.astype(np.int64) * px + c0.astype(np.int64)
            fx[take] = col - c0
            fy[take] = row - r0
            todo &= ~take
        half = self.halves[-1]
        outside = valid & ((np.abs(x) > half) | (np.abs(y) > half))
        return i00, fx, fy, int(outside.sum())


class HorizonMap:
    """One sun azimuth's horizon at the texels of ``geometry``: flat float32 planes (level after
    level, each row-major, row 0 = north, col 0 = west) of the slope tan(h), the occluder distance
    and the eye height (crater_core.horizon.horizon_maps)."""

    def __init__(
        self,
        values: np.ndarray,
        geometry: MapGeometry,
        distance: np.ndarray | None = None,
        eye_z: np.ndarray | None = None,
    ):
        self.values = values
        self.distance = distance
        self.eye_z = eye_z
        self.geometry = geometry


class GBuffer:
    __slots__ = ("normals", "view", "mu", "cov", "depth", "valid", "i00", "fx", "fy", "shape", "n_outside", "px", "z")

    def __init__(self, passes: dict, cam_position: np.ndarray, geometry: MapGeometry):
        cov = np.clip(passes["cov"], 0.0, 1.0).astype(np.float32)
        self.shape = cov.shape
        self.cov = cov
        self.depth = passes["Depth"].astype(np.float32)
        self.normals = direct.unit_normals(passes["Normal"])
        p_sum = passes["P"][..., :3].astype(np.float64)
        valid = cov > 1e-6
        pos = np.where(valid[..., None], p_sum / np.maximum(cov, 1e-6)[..., None], 0.0)
        view = cam_position[None, None, :] - pos
        view /= np.maximum(np.linalg.norm(view, axis=-1, keepdims=True), 1e-9)
        self.view = view.astype(np.float32)
        self.mu = np.einsum("...k,...k->...", self.normals, self.view).astype(np.float32)
        self.valid = valid
        self.z = pos[..., 2].astype(np.float32)
        i00, self.fx, self.fy, self.n_outside = geometry.locate(pos[..., 0], pos[..., 1], valid)
        self.i00 = i00.astype(np.int32)
        self.px = geometry.px

    def lookup(self, values) -> np.ndarray:
        """Bilinear lookup of a flat texel array (or a map's ``values``) at every pixel."""
        v = values.values if isinstance(values, HorizonMap) else values
        s = self.px
        a, b = v[self.i00], v[self.i00 + 1]
        c, d = v[self.i00 + s], v[self.i00 + s + 1]
        top = a + (b - a) * self.fx
        bot = c + (d - c) * self.fx
        return top + (bot - top) * self.fy


def horizon_cache_dir(job_value: str | None, terrain_npz: str) -> str:
    """Where a job's horizon maps are cached: the job's ``horizon_cache_dir``, or ``<terrain dir>/horizon``."""
    return job_value or os.path.join(os.path.dirname(os.path.abspath(terrain_npz)), "horizon")


def horizon_terrain(t: dict) -> horizon.Terrain:
    """The horizon computation's terrain from a loaded terrain npz (``blender_gen.job.load_terrain``)."""
    return horizon.Terrain(t["near_xyz"], t.get("far_xyz"), t.get("far_keep_quads"))


def ensure_horizons(terrain_npz: str, render_cfg: dict, diameter_m: float, azimuths, cache_dir: str, log=None):
    """The horizon maps a fast-mode job over ``terrain_npz`` needs (its geometry from ``render_cfg`` and the
    job's crater diameter), from the shared cache or computed into it: what a worker's
    :meth:`FastRenderer.prepare_horizons` reads. Needs no bpy, so a host may compute them ahead of its
    workers (the cache's lock files make each map computed once)."""
    geom = MapGeometry(
        float(render_cfg["shadow_map_extent_factor"]) * diameter_m,
        int(render_cfg["shadow_map_px"]),
        int(render_cfg["shadow_map_levels"]),
    )
    digest = horizon_cache.file_digest(terrain_npz)
    return horizon_cache.ensure_maps(
        lambda: horizon_terrain(load_terrain(terrain_npz)), digest, azimuths, geom.halves, geom.px, cache_dir, log=log
    )


class FastRenderer:
    def __init__(self, session, terrain_loader, gbuffer_cache_size: int = 256, horizon_cache_size: int = 64):
        self.s = session
        cfg = session.cfg
        self.half = float(cfg["shadow_map_extent_factor"]) * session.diameter_m
        self.map_px = int(cfg["shadow_map_px"])
        self.geometry = MapGeometry(self.half, self.map_px, int(cfg["shadow_map_levels"]))
        self.gbuffer_samples = int(cfg["gbuffer_samples"]) or int(cfg["samples"])
        self.gbuffers: OrderedDict = OrderedDict()
        self.gbuffer_cache_size = gbuffer_cache_size
        self.pixel_horizons: OrderedDict = OrderedDict()  # (camera key, azimuth) -> horizon per pixel
        self.horizon_cache_size = horizon_cache_size
        self.terrain_loader = terrain_loader
        self.horizon_maps: dict[float, HorizonMap] = {}
        if int(cfg["max_bounces"]) > 0:  # the factorisation is for direct sunlight only
            print(
                f"[blender_gen.fast] render.max_bounces={cfg['max_bounces']} ignored in fast mode (direct light only)",
                file=sys.stderr,
                flush=True,
            )
            session.scene.cycles.max_bounces = 0
            session.scene.cycles.diffuse_bounces = 0
        self.stats = {
            "horizon_maps": 0,
            "horizon_s": 0.0,
            "gbuffers": 0,
            "gbuffer_s": 0.0,
            "gbuffer_hits": 0,
            "shade_s": 0.0,
            "fallbacks": 0,
        }

    # -- per sun azimuth ------------------------------------------------------------------------
    def prepare_horizons(self, azimuths, terrain_npz: str, cache_dir: str, log=None) -> None:
        """Horizon maps of every sun azimuth of the job: from the shared on-disk cache, or computed
        once (crater_core.horizon_cache.ensure_maps: one process per azimuth, the others wait)."""
        t0 = time.perf_counter()
        digest = horizon_cache.file_digest(terrain_npz)

        def build():
            return horizon_terrain(self.terrain_loader())

        maps = horizon_cache.ensure_maps(build, digest, azimuths, self.geometry.halves, self.map_px, cache_dir, log=log)
        for az, m in maps.items():  # (levels, planes, px, px) -> one flat array per plane
            slope, dist, eye = (np.ascontiguousarray(m[:, k]).reshape(-1) for k in range(3))
            self.horizon_maps[az] = HorizonMap(slope, self.geometry, dist, eye)
        self.stats["horizon_maps"] += len(maps)
        self.stats["horizon_s"] += time.perf_counter() - t0

    def horizon_map(self, azimuth: float) -> HorizonMap:
        hm = self.horizon_maps.get(float(azimuth))
        if hm is None:
            raise KeyError(f"no horizon map for sun azimuth {azimuth} (prepare_horizons first)")
        return hm

    # -- per camera -----------------------------------------------------------------------------
    @staticmethod
    def camera_key(item: dict) -> tuple:
        return (
            float(item["cam_elevation"]),
            float(item["cam_azimuth"]),
            float(item["range_m"]),
            float(item["fov_deg"]),
            int(item["frame_width"]),
            tuple(int(c) for c in item["crop"]),
            # an explicit pose (navigation frames) is part of the camera
            json.dumps(item.get("camera"), sort_keys=True),
        )

    def get_gbuffer(self, item: dict) -> GBuffer:
        key = self.camera_key(item)
        g = self.gbuffers.get(key)
        if g is not None:
            self.gbuffers.move_to_end(key)
            self.stats["gbuffer_hits"] += 1
            return g
        t0 = time.perf_counter()
        self.s.configure("gbuffer", self.gbuffer_samples)
        p = self.s.render_view(item)
        g = GBuffer(p, self.s.pose(item).position, self.geometry)
        self.gbuffers[key] = g
        if len(self.gbuffers) > self.gbuffer_cache_size:
            self.gbuffers.popitem(last=False)
        self.stats["gbuffers"] += 1
        self.stats["gbuffer_s"] += time.perf_counter() - t0
        return g

    def pixel_horizon(self, item: dict, g: GBuffer) -> np.ndarray:
        """Horizon elevation (radians) for the item's sun azimuth at the 2 x 2 sub-pixel points
        (+-1/4 pixel) of every pixel, shape (4, h, w): the horizon at the pixel's mean surface point
        (corrected to its height on the mesh), extrapolated with its image-space gradient. Averaging the
        lit factor over them antialiases shadow edges sharper than a pixel (direct mode's 16 samples do
        the same)."""
        key = (self.camera_key(item), float(item["sun_azimuth"]))
        sub = self.pixel_horizons.get(key)
        if sub is None:
            hm = self.horizon_map(float(item["sun_azimuth"]))
            slope = horizon.pixel_slope(g.lookup(hm.values), g.lookup(hm.distance), g.lookup(hm.eye_z), g.z)
            h = np.arctan(slope).astype(np.float32)
            dv, du = np.gradient(h) if min(h.shape) > 1 else (np.zeros_like(h), np.zeros_like(h))
            sub = np.stack([h + a * du + b * dv for a in (-0.25, 0.25) for b in (-0.25, 0.25)]).astype(np.float32)
            self.pixel_horizons[key] = sub
            if len(self.pixel_horizons) > self.horizon_cache_size:
                self.pixel_horizons.popitem(last=False)
        return sub

    # -- per render -----------------------------------------------------------------------------
    def render(self, item: dict, to_sun: np.ndarray) -> dict[str, np.ndarray]:
        g = self.get_gbuffer(item)
        if g.n_outside:
            raise FallbackNeeded(
                f"{g.n_outside} px see terrain outside the horizon map (|x| or |y| > {self.half:.0f} m)"
            )
        t0 = time.perf_counter()
        h = self.pixel_horizon(item, g)
        theta = math.radians(float(item["sun_elevation"]))
        phi = math.radians(float(item["sun_azimuth"]))
        s = np.asarray(to_sun, dtype=np.float32)
        ds_dtheta = np.array(
            [-math.sin(theta) * math.sin(phi), -math.sin(theta) * math.cos(phi), math.cos(theta)], dtype=np.float32
        )
        mu0 = g.normals @ s
        sunward = g.valid & (mu0 > 0.0)
        lit = np.zeros(g.shape, dtype=np.float32)
        mu0_s, slope_s = mu0[sunward], g.normals[sunward] @ ds_dtheta
        lit[sunward] = horizon.mean_disc_lit_factor(theta, h[:, sunward], mu0_s, slope_s)
        m = sunward & (g.mu > 0.0) & (lit > 0.0)
        radiance = np.zeros(g.shape, dtype=np.float32)
        if m.any():
            radiance[m] = radiance_factor32(mu0[m], g.mu[m], g.view[m] @ s, self.s.params) * lit[m] * g.cov[m]
        lit_out = np.clip(lit, 0.0, 1.0)
        self.stats["shade_s"] += time.perf_counter() - t0
        return {
            "IF": radiance,
            "depth": g.depth,
            "N.X": g.normals[..., 0],
            "N.Y": g.normals[..., 1],
            "N.Z": g.normals[..., 2],
            "lit": lit_out,
        }


__all__ = ["FastRenderer", "FallbackNeeded", "HorizonMap", "GBuffer", "MapGeometry"]
