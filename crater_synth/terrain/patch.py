"""Terrain patch for rendering: a curved near field at fine spacing plus a coarse far field.

Contract with the Blender worker (docs/terrain.md):

- Frame: local ENU at the crater centre on the reference sphere (``crater_core.geometry``):
  x east, y north, z up, metres, origin on the sphere (height 0) below the crater centre.
- Near field: vertices over horizontal ENU (e, n) in [-hw, hw]^2, hw = near_radius_factor x D,
  ``terrain.near_vertices`` per side; row i <-> n_i = -hw + i * spacing (ascending north), column j
  <-> e_j = -hw + j * spacing (ascending east). Each vertex lies on the ray from the Moon's centre
  through origin + e E + n N, at radius R + h (h: DEM height, bicubic, + sub-DEM detail), expressed
  in ENU: the Moon's curvature is in the geometry (ground 100 km away is ~2.9 km below z = 0).
- Far field: the same construction without detail, spacing ``far_spacing_km``, out to
  ``far_radius_km`` (clipped to where the far DEM has data); ``far_keep_quads[i, j]`` is False for
  the quads lying fully inside the near field shrunk by one far cell, so near and far overlap by at
  least one far cell and leave no crack.
- ``<data_dir>/terrain/<crater>-<terrain_id>.npz`` (near_xyz, far_xyz, far_keep_quads, near_height)
  and ``.json`` (metadata) are written atomically, npz first; a patch with the same terrain_id is
  reused.
"""

from __future__ import annotations

import io
import json
import math
import time
from pathlib import Path

import click
import numpy as np

from crater_core.files import ensure_writable_dir
from crater_core.geometry import MOON_RADIUS_M, mc_to_enu
from crater_core.schema import atomic_write_bytes, atomic_write_json, content_key
from crater_core.settings import NEAR_VERTICES_RANGE  # noqa: F401 - the range lives with the settings
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import as_settings, load_settings
from crater_synth.errors import UserError
from crater_synth.terrain import stack
from crater_synth.terrain.dem import Dem, DemCoverageError, check_hemisphere
from crater_synth.terrain.detail import synthesize_detail
from crater_synth.terrain.grid import bilinear, sphere_points
from data_manifest.products import cached_sha256, resolve_product

# Bump when the patch arrays or their meaning change: it is part of every terrain_id.
TERRAIN_FORMAT_VERSION = 1
TERRAIN_SUBDIR = "terrain"
# Rim/floor measurement (docs/terrain.md): rim crest = max of each radial profile between these
# fractions of the radius, averaged over azimuth; floor = low percentile within FLOOR_RADIUS_FRAC R.
RIM_SEARCH_FRAC = (0.9, 1.1)
FLOOR_RADIUS_FRAC = 0.3
FLOOR_PERCENTILE = 5.0
N_AZIMUTHS = 360


class TerrainConfigError(UserError):
    """A terrain.* or dem.* setting is missing or out of range."""


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------
def terrain_settings(cfg) -> dict:
    """``terrain.*`` (without ``detail``), ``detail``, ``dem.*`` and ``data_dir`` of the typed settings
    (a raw configuration is converted, and so validated, once: crater_core/settings.py)."""

    st = as_settings(cfg)
    t, d = st.terrain, st.dem
    s = {
        "near_radius_factor": t.near_radius_factor,
        "near_vertices": t.near_vertices,
        "far_radius_km": t.far_radius_km,
        "far_spacing_km": t.far_spacing_km,
        "max_nodata_fraction": d.max_nodata_fraction,
        "detail": t.detail,
        "dem": {
            "product": d.product,
            "path": d.path,
            "far_product": d.far_product,
            "far_path": d.far_path,
            "stack": list(d.stack),
            "blend_pixels": d.blend_pixels,
        },
    }
    s["data_dir"] = Path(str(st.data_dir)).expanduser().resolve()  # absolute: workers run elsewhere
    return s


def _crater_dict(crater) -> dict:
    """A crater entry (``CraterSettings`` or its dict) as the plain dict the patch metadata records."""
    return crater.as_dict() if hasattr(crater, "as_dict") else dict(crater)


def open_stack(s: dict):
    """The near-field DEM: the base (dem.product / dem.path) with the dem.stack layers over it."""

    base, base_sha = open_dem(s["dem"]["product"], s["dem"]["path"], s["data_dir"])
    return stack.open_stack(base, base_sha, s["dem"]["stack"], s["data_dir"], s["dem"]["blend_pixels"]), base_sha


def open_dem_stack(cfg):
    """The near-field DEM stack of the settings ``cfg`` (dem.product or dem.path, with dem.stack over it)."""
    return open_stack(terrain_settings(cfg))[0]


def stack_detail(shape: tuple[int, int], spacing_m: float, sample, settings, key: str) -> tuple[np.ndarray, dict]:
    """Sub-DEM detail weighted by the data behind each vertex (docs/dem_stack.md).

    For each DEM layer with weight W_k > 0 somewhere, ``synthesize_detail`` is called with that layer's
    effective pixel (native x decimation), and the fields are summed with the weights: where a
    layer as fine as the grid covers a vertex (e.g. the 200 m Shackleton crop on a 205 m grid) the
    detail is zero; where only the 1600 m base covers, it is the base's detail unchanged; across a
    blend band it fades with the weight. A plain :class:`SampleResult` (one DEM) gets the base's detail.
    """

    weights = getattr(sample, "layer_weights", None) or [np.ones(shape)]
    pixels = getattr(sample, "layer_pixel_m", None) or [None]
    base_px = pixels[0] if pixels[0] is not None else None
    field_sum = np.zeros(shape)
    by_pixel: dict[float, np.ndarray] = {}
    base_stats: dict = {}
    for i, (w, px) in enumerate(zip(weights, pixels)):
        if i > 0 and not np.any(w > 0.0):
            continue
        if px not in by_pixel:
            by_pixel[px], stats = synthesize_detail(shape, spacing_m, px, settings, key=key)
            if i == 0:
                base_stats = stats
        field_sum += w * by_pixel[px]
    if len(weights) == 1:
        return field_sum, base_stats
    base_stats = dict(base_stats)
    base_stats["stack"] = {
        "base_pixel_m": base_px,
        "base_weight_mean": float(np.mean(weights[0])),
        "rms_height_m": float(np.sqrt(np.mean(field_sum**2))),
        "note": "detail scaled by each DEM layer's weight; synthesised only below that layer's resolution",
    }
    return field_sum, base_stats


def open_dem(product: str | None, path: str | None, data_dir: Path):
    """(Dem, sha256) for a registry product or an explicit file (``path`` wins)."""

    if path:
        p = Path(str(path)).expanduser()
        dem = Dem(p, product=p.name)  # raises DemReadError naming a missing/corrupt file
        return dem, cached_sha256(p)
    p = resolve_product(str(product), data_dir)
    return Dem(p, product=str(product)), cached_sha256(p)


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------
def _to_enu(dirs: np.ndarray, heights: np.ndarray, lat: float, lon: float) -> np.ndarray:

    return mc_to_enu(dirs * (MOON_RADIUS_M + heights)[..., None], lat, lon)


def measure_crater(height: np.ndarray, z: np.ndarray, half_width: float, spacing: float, radius_m: float) -> dict:
    """Rim and floor from the patch (heights above the sphere, and ENU z).

    rim_z_m: mean ENU z on the ring r = D/2 (the rim circle the projected ellipse uses);
    rim crest: per-azimuth max of the radial profile over [0.9, 1.1] R, averaged;
    floor: 5th percentile within 0.3 R; depth = rim crest - floor (heights above the sphere, so
    the curvature drop across the crater does not bias it).
    """
    az = np.radians(np.arange(N_AZIMUTHS) * 360.0 / N_AZIMUTHS)
    sa, ca = np.sin(az), np.cos(az)
    rim_z = float(bilinear(z, half_width, spacing, radius_m * sa, radius_m * ca).mean())
    rim_h_ring = float(bilinear(height, half_width, spacing, radius_m * sa, radius_m * ca).mean())
    radii = np.linspace(RIM_SEARCH_FRAC[0], RIM_SEARCH_FRAC[1], 21) * radius_m
    prof = bilinear(height, half_width, spacing, np.outer(sa, radii), np.outer(ca, radii))
    rim_crest = float(prof.max(axis=1).mean())
    fr = np.linspace(0.0, FLOOR_RADIUS_FRAC, 16) * radius_m
    fe, fn = np.outer(sa, fr), np.outer(ca, fr)
    floor_h = float(np.percentile(bilinear(height, half_width, spacing, fe, fn), FLOOR_PERCENTILE))
    floor_z = float(np.percentile(bilinear(z, half_width, spacing, fe, fn), FLOOR_PERCENTILE))
    return {
        "rim_z_m": rim_z,
        "rim_height_m": rim_h_ring,
        "rim_crest_height_m": rim_crest,
        "floor_z_m": floor_z,
        "floor_height_m": floor_h,
        "rim_to_floor_depth_m": rim_crest - floor_h,
    }


def far_keep_quads(far_coords: np.ndarray, near_half_width: float, far_spacing: float) -> np.ndarray:
    """(m-1, m-1) bool: False for quads fully inside the near square shrunk by one far cell."""
    inner = near_half_width - far_spacing
    ins = np.abs(far_coords) <= inner + 1e-6
    inside_1d = ins[:-1] & ins[1:]  # both edges of the cell inside
    return ~(inside_1d[:, None] & inside_1d[None, :])


def _far_half_cells(dem, lat: float, lon: float, k_max: int, spacing: float, max_nodata: float) -> tuple[int, int]:
    """Largest Chebyshev ring index m <= k_max whose square lies inside the DEM with a nodata share
    <= max_nodata; returns (m, nodata vertices within it)."""
    k = np.arange(-k_max, k_max + 1) * spacing
    ee, nn = np.meshgrid(k, k)
    _, plat, plon = sphere_points(ee, nn, lat, lon)
    inside, valid = dem.coverage(plat, plon, spacing_m=spacing)
    ring = np.maximum(np.abs(np.arange(-k_max, k_max + 1))[None, :], np.abs(np.arange(-k_max, k_max + 1))[:, None])
    total = np.bincount(ring.ravel(), minlength=k_max + 1).cumsum()
    outside = np.bincount(ring.ravel(), weights=(~inside).ravel(), minlength=k_max + 1).cumsum()
    nodata = np.bincount(ring.ravel(), weights=(inside & ~valid).ravel(), minlength=k_max + 1).cumsum()
    ok = (outside == 0) & (nodata <= max_nodata * total)
    # Rings are nested: the largest m such that every ring up to m is acceptable.
    bad = np.flatnonzero(~ok)
    m = k_max if bad.size == 0 else int(bad[0]) - 1
    return m, (int(nodata[m]) if m >= 0 else 0)


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------
def _atomic_save_npz(path: Path, arrays: dict) -> None:
    """``np.savez`` through :func:`crater_core.schema.atomic_write_bytes` (temp file + rename)."""

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def terrain_id(dem_sha: str, far_dem_sha: str, crater: dict, s: dict, stack_key: dict | None = None) -> str:
    """Content key of a patch: DEM bytes (base, far and every stack layer with its blending), crater,
    terrain + detail settings, format version. An empty stack leaves the key as it was before stacks."""
    detail = s["detail"].as_dict() if s["detail"].enabled else {"enabled": False}
    key = {
        "format": TERRAIN_FORMAT_VERSION,
        "dem_sha256": dem_sha,
        "far_dem_sha256": far_dem_sha,
        "crater": {k: crater[k] for k in ("name", "lat", "lon", "diameter_km")},
        "terrain": {
            k: s[k]
            for k in ("near_radius_factor", "near_vertices", "far_radius_km", "far_spacing_km", "max_nodata_fraction")
        },
        "detail": detail,
    }
    if stack_key and stack_key.get("layers"):
        key["stack"] = stack_key
    return content_key(key)


def _load_cached(npz: Path, meta_path: Path, tid: str) -> dict | None:
    if not (npz.is_file() and meta_path.is_file()):
        return None
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    return meta if meta.get("terrain_id") == tid else None


def _open_dems(s: dict, name: str, lat: float):
    """The near-field DEM stack and the far-field DEM (the same stack unless ``dem.far_*`` names one),
    each checked to cover the crater's hemisphere: (dem, its sha256, far DEM, its sha256)."""

    dem, dem_sha = open_stack(s)
    check_hemisphere(dem, name, lat)
    if s["dem"]["far_product"] or s["dem"]["far_path"]:
        far_dem, far_sha = open_dem(s["dem"]["far_product"], s["dem"]["far_path"], s["data_dir"])
        check_hemisphere(far_dem, name, lat)
    else:
        far_dem, far_sha = dem, dem_sha  # the same stack: near and far fields agree in their overlap
    return dem, dem_sha, far_dem, far_sha


def _crater_pixel(dem, name: str, lat: float, lon: float) -> tuple:
    """The crater centre's (col, row) in ``dem``; a centre outside the DEM is a coverage error."""

    ccol, crow = dem.latlon_to_pixel(lat, lon)
    if not bool(dem.inside(ccol, crow)):
        raise DemCoverageError(
            f"crater {name} at (lat {lat:g}, lon {lon:g}) lies outside DEM {dem.product} "
            f"(pixel col {float(ccol):.1f}, row {float(crow):.1f} of {dem.width}x{dem.height})"
        )
    return ccol, crow


def _near_field(dem, s: dict, name: str, lat: float, lon: float, diameter_m: float):
    """The near-field grid: DEM heights plus sub-DEM detail, as ENU vertices. Returns (half width m,
    spacing m, east grid, north grid, the DEM sample, heights, ENU vertices, detail stats)."""
    nv = s["near_vertices"]
    hw = s["near_radius_factor"] * diameter_m
    spacing = 2.0 * hw / (nv - 1)
    coords = np.linspace(-hw, hw, nv)
    ee, nn = np.meshgrid(coords, coords)  # [i, j] = (e_j, n_i)
    dirs, plat, plon = sphere_points(ee, nn, lat, lon)
    near = dem.sample(
        plat,
        plon,
        spacing_m=spacing,
        max_nodata_fraction=s["max_nodata_fraction"],
        what=f"near field of crater {name} (+-{hw / 1e3:.1f} km)",
    )
    detail, detail_stats = stack_detail((nv, nv), spacing, near, s["detail"], key=name)
    near_h = near.heights + detail
    near_xyz = _to_enu(dirs, near_h, lat, lon)
    return hw, spacing, ee, nn, near, near_h, near_xyz, detail_stats


def _far_field(far_dem, s: dict, name: str, lat: float, lon: float, hw: float):
    """The far-field grid beyond the near field's half width ``hw`` (empty when
    ``terrain.far_radius_km`` is 0): (ENU vertices, quads to keep, its metadata)."""

    fs = s["far_spacing_km"] * 1000.0
    far_info: dict = {"half_width_m": 0.0, "spacing_m": fs, "shape": [0, 0], "product": far_dem.product}
    if not s["far_radius_km"] > 0.0:
        return np.zeros((0, 0, 3)), np.zeros((0, 0), dtype=bool), far_info
    k_max = int(math.floor(s["far_radius_km"] * 1000.0 / fs + 1e-9))
    k_min = int(math.ceil(hw / fs + 1e-9)) + 1  # at least one far ring wholly outside the near field
    if k_max < k_min:
        raise TerrainConfigError(
            f"terrain.far_radius_km={s['far_radius_km']:g} does not reach beyond the near field of crater "
            f"{name} (+-{hw / 1e3:.1f} km) by one far cell ({fs / 1e3:g} km); raise it or set it to 0"
        )
    m, _ = _far_half_cells(far_dem, lat, lon, k_max, fs, s["max_nodata_fraction"])
    if m < k_min:
        raise DemCoverageError(
            f"DEM {far_dem.product} does not cover a far field around crater {name} beyond its near field "
            f"(+-{hw / 1e3:.1f} km + one {fs / 1e3:g} km cell); set dem.far_product to a wider DEM or "
            "terrain.far_radius_km=0"
        )
    fcoords = np.arange(-m, m + 1) * fs
    fe, fn = np.meshgrid(fcoords, fcoords)
    fdirs, flat, flon = sphere_points(fe, fn, lat, lon)
    far = far_dem.sample(
        flat,
        flon,
        spacing_m=fs,
        max_nodata_fraction=s["max_nodata_fraction"],
        what=f"far field of crater {name} (+-{m * fs / 1e3:.0f} km)",
    )
    keep = far_keep_quads(fcoords, hw, fs)
    far_info.update(
        half_width_m=float(m * fs),
        shape=[2 * m + 1, 2 * m + 1],
        requested_half_width_m=float(k_max * fs),
        clipped=bool(m < k_max),
        nodata_fraction=far.nodata_fraction,
        filled_pixels=far.filled_pixels,
        filled_holes=far.filled_holes,
        decimation=far.decimation,
        kept_quads=int(keep.sum()),
    )
    return _to_enu(fdirs, far.heights, lat, lon), keep, far_info


def _dem_meta(dem, dem_sha: str, far_dem, far_sha: str, pixel, near, ee, nn, radius_m: float) -> dict:
    """The patch metadata's ``dem`` entry: the products, their checksums and CRS, the crater's pixel."""
    dem_info = dem.info()
    return {
        "product": dem.product,
        "path": str(dem.path),
        "sha256": dem_sha,
        "pixel_size_m": dem.pixel_size_m,
        "crs_wkt": dem_info["crs_wkt"],
        "crs_proj": dem_info["crs_proj"],
        "crater_center_px": [float(pixel[0]), float(pixel[1])],
        "decimation": near.decimation,
        "far_product": far_dem.product,
        "far_sha256": far_sha,
        "stack": _stack_meta(dem, near, ee, nn, radius_m),
        "blend_pixels": dem.blend_pixels,
    }


def build_terrain(crater, cfg) -> tuple[Path, dict]:
    """Build (or reuse) the terrain patch of ``crater`` (a ``CraterSettings`` of ``settings.craters``, or
    its dict) for the settings ``cfg`` (``Settings``; a raw configuration is converted once).

    Returns (npz path, metadata dict as written to the sibling ``.json``).
    """

    t0 = time.perf_counter()
    s = terrain_settings(cfg)
    crater = _crater_dict(crater)
    name, lat, lon = str(crater["name"]), float(crater["lat"]), float(crater["lon"])
    diameter_m = float(crater["diameter_km"]) * 1000.0
    dem, dem_sha, far_dem, far_sha = _open_dems(s, name, lat)

    tid = terrain_id(dem_sha, far_sha, crater, s, dem.key())
    out_dir = s["data_dir"] / TERRAIN_SUBDIR
    ensure_writable_dir(s["data_dir"], "data_dir")
    npz_path = out_dir / f"{name}-{tid}.npz"
    meta_path = npz_path.with_suffix(".json")
    cached = _load_cached(npz_path, meta_path, tid)
    if cached is not None:
        return npz_path, {**cached, "patch": str(npz_path), "cached": True}

    pixel = _crater_pixel(dem, name, lat, lon)
    hw, spacing, ee, nn, near, near_h, near_xyz, detail_stats = _near_field(dem, s, name, lat, lon, diameter_m)
    far_xyz, keep, far_info = _far_field(far_dem, s, name, lat, lon, hw)
    meas = measure_crater(near_h, near_xyz[..., 2], hw, spacing, 0.5 * diameter_m)
    arrays = {
        "near_xyz": near_xyz.astype(np.float32),
        "far_xyz": far_xyz.astype(np.float32),
        "far_keep_quads": keep.astype(bool),
        "near_height": near_h.astype(np.float32),
    }
    nv = s["near_vertices"]
    meta = {
        "terrain_id": tid,
        "format_version": TERRAIN_FORMAT_VERSION,
        "crater": {k: crater[k] for k in ("name", "lat", "lon", "diameter_km", "source") if k in crater},
        "frame": "ENU at the crater centre on the 1737.4 km sphere; x east, y north, z up, metres",
        "dem": _dem_meta(dem, dem_sha, far_dem, far_sha, pixel, near, ee, nn, 0.5 * diameter_m),
        "near": {
            "half_width_m": hw,
            "spacing_m": spacing,
            "shape": [nv, nv],
            "rows": "n ascending (south to north)",
            "cols": "e ascending (west to east)",
        },
        "far": far_info,
        **{k: meas[k] for k in ("rim_z_m", "floor_z_m", "rim_to_floor_depth_m")},
        "rim_height_m": meas["rim_height_m"],
        "rim_crest_height_m": meas["rim_crest_height_m"],
        "floor_height_m": meas["floor_height_m"],
        "vertex_count": int(nv * nv + far_xyz.shape[0] * far_xyz.shape[1]),
        "nodata_fraction": near.nodata_fraction,
        "filled_holes": near.filled_holes,
        "filled_pixels": near.filled_pixels,
        "detail": detail_stats,
        "patch": str(npz_path),
        "build_seconds": round(time.perf_counter() - t0, 3),
    }
    _atomic_save_npz(npz_path, arrays)
    atomic_write_json(meta_path, meta)
    return npz_path, {**meta, "cached": False}


def _stack_meta(stack, near, ee: np.ndarray, nn: np.ndarray, radius_m: float) -> list[dict]:
    """Per stack layer: its identity and blending, and its weight over the near field and the crater."""
    in_crater = np.hypot(ee, nn) <= RIM_SEARCH_FRAC[1] * radius_m
    out = []
    for i, info in enumerate(stack.stack_info()):  # sample weights: base first, then the layers finest first
        w = near.layer_weights[i + 1]
        out.append(
            {
                **info,
                "near_weight_mean": round(float(w.mean()), 4),
                "crater_weight_mean": round(float(w[in_crater].mean()), 4),
                "effective_pixel_m": float(near.layer_pixel_m[i + 1]),
            }
        )
    return out


def summary_line(meta: dict) -> dict:
    """The one-line JSON report of a patch printed by ``crater-synth terrain``."""
    return {
        "crater": meta["crater"]["name"],
        "terrain_id": meta["terrain_id"],
        "dem_product": meta["dem"]["product"],
        "dem_pixel_m": meta["dem"]["pixel_size_m"],
        "crater_center_px": [round(v, 3) for v in meta["dem"]["crater_center_px"]],
        "rim_to_floor_depth_m": round(meta["rim_to_floor_depth_m"], 1),
        "rim_z_m": round(meta["rim_z_m"], 1),
        "near_extent_km": round(2.0 * meta["near"]["half_width_m"] / 1e3, 3),
        "near_spacing_m": round(meta["near"]["spacing_m"], 2),
        "far_extent_km": round(2.0 * meta["far"]["half_width_m"] / 1e3, 3),
        "vertex_count": meta["vertex_count"],
        "nodata_fraction": meta["nodata_fraction"],
        "filled_holes": meta["filled_holes"],
        "detail_craters": meta["detail"]["n_craters"],
        "dem_stack": [layer["product"] for layer in meta["dem"].get("stack", [])],
        "fine_weight_crater": round(sum(layer["crater_weight_mean"] for layer in meta["dem"].get("stack", [])), 3),
        "cached": meta.get("cached", False),
        "patch": meta["patch"],
    }


@click.command("terrain")
@OVERRIDES
@user_errors
def terrain_command(overrides):
    """Build (or reuse) each selected crater's terrain patch; print one JSON line per crater.

    Example: `crater-synth terrain crater=shackleton terrain.near_vertices=256`
    """

    settings = load_settings(overrides)
    ensure_writable_dir(settings.data_dir, "data_dir")
    for crater in settings.craters:
        _, meta = build_terrain(crater, settings)
        click.echo(json.dumps(summary_line(meta)))
