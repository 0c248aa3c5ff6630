"""Fast (production) mode: the sweep's sun x camera factorisation (SPEC.md, Performance notes).

Per sun direction (renders arrive sun-major, so one map is live at a time):
    a terrain-space *lit map*: orthographic top-down Cycles renders of the terrain over nested
    squares (``shadow_map_levels``, the outer one |x|, |y| <= shadow_map_extent_factor x D, each
    ``shadow_map_px``^2) with the material in "lit" mode (Diffuse colour 1 / max(mu0, eps), sun on).
    Each texel is Cycles' estimate of <max(N.l, 0) V(l)>_disk / mu0, the same quantity the direct
    render multiplies the Hapke radiance factor by, averaged over the texel: cast shadows (near *and*
    far field, the lamp's finite disk) all come from Cycles.
Per camera pose (cached in-process, LRU):
    a *G-buffer*: a Cycles render of the crop with the material in "gbuffer" mode (sun off), giving
    the pixel-averaged shading normal, the mean surface point P (AOV) and terrain coverage (AOV),
    and depth. From them: view vectors v = unit(camera - P), mu = N.v, and the bilinear lookup of P's
    (x, y) into the lit map (same texel geometry for every sun, so indices/weights are cached).
Per render (numpy only):
    I/F = cov * hapke.radiance_factor(mu0 = N.s, mu, cos g = v.s) * lit(P.xy)
with the numpy backend of the same formula the shader nodes are generated from.

Differences from direct mode (docs/renderer.md quantifies them): the Hapke term is evaluated once per
pixel at the mean normal instead of per sample (matters only where a pixel straddles a crease or an
occluding edge), and shadow edges are resampled from the lit map's texels (texel < pixel by default).
Direct light only: ``max_bounces`` is forced to 0 here.
"""

from __future__ import annotations

import sys
import time
from collections import OrderedDict

import numpy as np

from blender_gen import direct
from crater_core import hapke

LIT_MAP_MAX = 4.0  # clip of the map before interpolation (>1 only within ~one solar radius of the terminator)


class FallbackNeeded(Exception):
    """The crop sees terrain outside the lit map: render this image in direct mode instead."""


class MapGeometry:
    """Nested square lit maps ("levels"), all ``px`` x ``px`` texels, centred on the crater: level k
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


class LitMap:
    def __init__(self, values: np.ndarray, geometry: MapGeometry):
        self.values = values  # flat float32: level after level, each row-major (row 0 = north, col 0 = west)
        self.geometry = geometry


class GBuffer:
    __slots__ = ("normals", "view", "mu", "cov", "depth", "valid", "i00", "fx", "fy", "shape", "n_outside", "px")

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
        i00, self.fx, self.fy, self.n_outside = geometry.locate(pos[..., 0], pos[..., 1], valid)
        self.i00 = i00.astype(np.int32)
        self.px = geometry.px

    def lookup(self, lit_map: LitMap) -> np.ndarray:
        v = lit_map.values
        s = self.px
        a, b = v[self.i00], v[self.i00 + 1]
        c, d = v[self.i00 + s], v[self.i00 + s + 1]
        top = a + (b - a) * self.fx
        bot = c + (d - c) * self.fx
        return top + (bot - top) * self.fy


class FastRenderer:
    def __init__(self, session, gbuffer_cache_size: int = 256):
        self.s = session
        cfg = session.cfg
        self.half = float(cfg["shadow_map_extent_factor"]) * session.diameter_m
        self.map_px = int(cfg["shadow_map_px"])
        self.geometry = MapGeometry(self.half, self.map_px, int(cfg["shadow_map_levels"]))
        self.map_samples = int(cfg["shadow_map_samples"]) or int(cfg["samples"])
        self.gbuffer_samples = int(cfg["gbuffer_samples"]) or int(cfg["samples"])
        self.gbuffers: OrderedDict = OrderedDict()
        self.gbuffer_cache_size = gbuffer_cache_size
        if int(cfg["max_bounces"]) > 0:  # the factorisation is for direct sunlight only
            print(f"[blender_gen.fast] render.max_bounces={cfg['max_bounces']} ignored in fast mode "
                  "(direct light only)", file=sys.stderr, flush=True)
            session.scene.cycles.max_bounces = 0
            session.scene.cycles.diffuse_bounces = 0
        self.lit_key = None
        self.lit_map: LitMap | None = None
        self.stats = {"lit_maps": 0, "lit_map_s": 0.0, "gbuffers": 0, "gbuffer_s": 0.0, "gbuffer_hits": 0,
                      "shade_s": 0.0, "fallbacks": 0}

    # -- per sun --------------------------------------------------------------------------------
    def get_lit_map(self, to_sun: np.ndarray) -> LitMap:
        key = tuple(np.round(np.asarray(to_sun, dtype=np.float64), 12))
        if key != self.lit_key:
            t0 = time.perf_counter()
            self.s.set_sun(to_sun)
            self.s.configure("lit", self.map_samples)
            levels = [self.s.render_top_down(half, self.map_px)["Combined"][..., 0] for half in self.geometry.halves]
            values = np.clip(np.concatenate([lv.ravel() for lv in levels]), 0.0, LIT_MAP_MAX).astype(np.float32)
            self.lit_map = LitMap(values, self.geometry)
            self.lit_key = key
            self.stats["lit_maps"] += 1
            self.stats["lit_map_s"] += time.perf_counter() - t0
        return self.lit_map

    # -- per camera -----------------------------------------------------------------------------
    def get_gbuffer(self, item: dict) -> GBuffer:
        key = (float(item["cam_elevation"]), float(item["cam_azimuth"]), float(item["range_m"]),
               float(item["fov_deg"]), int(item["frame_width"]), tuple(int(c) for c in item["crop"]))
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

    # -- per render -----------------------------------------------------------------------------
    def render(self, item: dict, to_sun: np.ndarray) -> dict[str, np.ndarray]:
        g = self.get_gbuffer(item)
        if g.n_outside:
            raise FallbackNeeded(f"{g.n_outside} px see terrain outside the lit map "
                                 f"(|x| or |y| > {self.half:.0f} m)")
        lm = self.get_lit_map(to_sun)
        t0 = time.perf_counter()
        s = np.asarray(to_sun, dtype=np.float32)
        mu0 = g.normals @ s
        cos_g = g.view @ s
        lit = g.lookup(lm)
        m = g.valid & (mu0 > 0.0) & (g.mu > 0.0)
        radiance = np.zeros(g.shape, dtype=np.float32)
        if m.any():
            radiance[m] = hapke.radiance_factor_np(mu0[m], g.mu[m], cos_g[m], self.s.params) * lit[m] * g.cov[m]
        lit_out = np.where(g.valid & (mu0 > 0.0), np.clip(lit, 0.0, 1.0), 0.0).astype(np.float32)
        self.stats["shade_s"] += time.perf_counter() - t0
        return {"IF": radiance, "depth": g.depth,
                "N.X": g.normals[..., 0], "N.Y": g.normals[..., 1], "N.Z": g.normals[..., 2],
                "lit": lit_out}


__all__ = ["FastRenderer", "FallbackNeeded", "LitMap", "GBuffer"]
