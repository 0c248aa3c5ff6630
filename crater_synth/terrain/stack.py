"""Multi-resolution DEM stack: finer DEMs where they exist, the base DEM everywhere else, blended
with no seam or step (docs/dem_stack.md).

A :class:`DemStack` has the sampling interface of :class:`crater_synth.terrain.dem.Dem` (``sample``,
``coverage``, ``latlon_to_pixel``, ``inside``, ``info``, ``product``, ``pixel_size_m``...). It holds
a base DEM (which must cover every query, as before) and an ordered list of layers, finest first;
each layer is any DEM :class:`Dem` opens (a registered product or a user GeoTIFF / PDS3 file).

Blending, per query point, from the coarsest layer to the finest::

    h <- base heights
    for each layer k, coarsest first:   h <- h + w_k (h_k - h)

The weight w_k is 1 deep inside the layer's valid data and falls to exactly 0 at its edge (raster
edge or nodata) with a C1 profile:

- D = Euclidean distance (m) from the layer's outermost valid pixel centres inwards (EDT of the
  valid mask, read around the query at a cell of at most band / 8);
- D_s = D smoothed by a Gaussian of sigma = band / 4 (removes the distance field's kinks at
  corners and along medial axes, so w has continuous gradients everywhere);
- w = raised cosine of clip((D_s - sigma / 2) / band, 0, 1): 0 for D_s <= sigma / 2, which holds on
  and outside the valid edge (a smoothed ramp is <= 0.4 sigma there), 1 beyond band + sigma / 2.

band_k = ``dem.blend_pixels`` x the pixel of the coarser data under the layer: the first later
(coarser) layer whose full-weight core contains layer k's whole raster, else the base DEM. So with
the default 1.5 a 200 m layer on the 1600 m base fades in over 2.4 km, a 40 m layer inside it over 300 m.

Heights are continuous with continuous gradients: h and w are C1 and h_k is a cubic B-spline.
Every sample also carries the final weight of each layer (``layer_weights``: w_k times the
(1 - w_j) of every finer layer j; the base's weight is what is left) and the layer's effective pixel
(native pixel x the anti-alias decimation of that query): ``terrain.py`` scales the sub-DEM detail
with them, so no synthetic detail is added on top of real fine data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rasterio.warp import transform

from crater_core.settings import BLEND_PIXELS_RANGE  # the allowed dem.blend_pixels, checked with the settings
from crater_synth.errors import UserError
from crater_synth.terrain.dem import Dem, SampleResult
from data_manifest.products import cached_sha256, load_products, resolve_product

# Distance-field cell: at most band / DISTANCE_CELLS_PER_BAND (resolution of the weight ramp).
DISTANCE_CELLS_PER_BAND = 8
# Smoothing of the distance field, and the dead zone that keeps w = 0 on the valid edge.
SMOOTH_SIGMA_PER_BAND = 0.25
DEAD_ZONE_PER_SIGMA = 0.5
# Gaussian support read beyond the band (in sigmas).
GAUSS_SUPPORT_SIGMAS = 4.0
# Default transition band, in coarse pixels (docs/dem_stack.md: on Shackleton, 1.5 keeps the whole
# rim circle at full 200 m weight; 2 already lets the 1600 m DEM into 10 % of it).
DEFAULT_BLEND_PIXELS = 1.5


class DemStackConfigError(UserError):
    """A dem.stack entry or dem.blend_pixels value is not usable."""


@dataclass
class StackSample(SampleResult):
    """:class:`SampleResult` of the base DEM with the blended heights, plus per-layer weights."""

    layer_names: list = field(default_factory=list)  # base first, then layers finest first
    layer_weights: list = field(default_factory=list)  # final weight per layer, shape of the query
    layer_pixel_m: list = field(default_factory=list)  # effective pixel (native x decimation), m

    @property
    def fine_weight(self) -> np.ndarray:
        """Share of each height that comes from layers finer than the base (0 = base DEM only)."""
        return 1.0 - self.layer_weights[0]

    @property
    def effective_pixel_m(self) -> np.ndarray:
        """Weighted effective pixel size (m) of the data behind each height."""
        return sum(w * p for w, p in zip(self.layer_weights, self.layer_pixel_m))


def raised_cosine(t: np.ndarray) -> np.ndarray:
    """0 at t <= 0, 1 at t >= 1, 0.5 - 0.5 cos(pi t) between (C1: zero slope at both ends)."""
    t = np.clip(t, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * t)


class _Layer:
    def __init__(self, dem: Dem, sha256: str, entry: str):
        self.dem = dem
        self.sha256 = sha256
        self.entry = entry
        self.band_m = 0.0
        self.under = ""

    @property
    def sigma_m(self) -> float:
        return SMOOTH_SIGMA_PER_BAND * self.band_m

    @property
    def dead_m(self) -> float:
        return DEAD_ZONE_PER_SIGMA * self.sigma_m

    def boundary_latlon(self, n: int = 16):
        """(lat, lon) of points along the hull of the layer's pixel centres."""
        d = self.dem
        t = np.linspace(0.0, 1.0, n)
        cols = np.concatenate(
            [0.5 + t * (d.width - 1), np.full(n, d.width - 0.5), 0.5 + t * (d.width - 1), np.full(n, 0.5)]
        )
        rows = np.concatenate(
            [np.full(n, 0.5), 0.5 + t * (d.height - 1), np.full(n, d.height - 0.5), 0.5 + t * (d.height - 1)]
        )
        tr = d.transform
        x, y = tr.c + tr.a * cols, tr.f + tr.e * rows
        lon, lat = transform(d.crs, d.geographic_crs, x, y)
        return np.asarray(lat), np.asarray(lon)

    def contains_core(self, lat, lon) -> bool:
        """True when all (lat, lon) lie inside this layer's full-weight core (raster hull shrunk by
        band + dead zone; nodata inside the raster is not considered)."""
        col, row = self.dem.latlon_to_pixel(lat, lon)
        inset = (self.band_m + self.dead_m + self.sigma_m) / self.dem.pixel_size_m + 0.5
        return bool(
            ((col >= inset) & (col <= self.dem.width - inset) & (row >= inset) & (row <= self.dem.height - inset)).all()
        )

    def weight(self, lat, lon) -> np.ndarray:
        """Blend weight w in [0, 1] at (lat, lon) (module docstring)."""
        from scipy import ndimage

        d = self.dem
        col, row = d.latlon_to_pixel(lat, lon)
        inside = d.inside(col, row)
        w = np.zeros(col.shape)
        if not inside.any():
            return w
        p = d.pixel_size_m
        factor = max(1, math.floor(self.band_m / DISTANCE_CELLS_PER_BAND / p))
        reach_m = self.band_m + self.dead_m + GAUSS_SUPPORT_SIGMAS * self.sigma_m
        margin = math.ceil(reach_m / p) + 2 * factor
        _, valid, (c0, r0), (h, wd) = d._read_window(col[inside], row[inside], factor, margin_px=margin)
        # Outside the raster is invalid: pad one invalid cell on each side where the window meets the
        # raster edge (elsewhere the window continues with its edge cells). The window holds whole
        # cells only, so it may stop short of the raster's far edge by less than one cell: that counts
        # as meeting it (the weight then reaches 0 up to one cell early, never late).
        edges = (r0 == 0, r0 + h > d.height - factor, c0 == 0, c0 + wd > d.width - factor)
        padded = np.pad(valid, 1, mode="edge")
        if edges[0]:
            padded[0, :] = False
        if edges[1]:
            padded[-1, :] = False
        if edges[2]:
            padded[:, 0] = False
        if edges[3]:
            padded[:, -1] = False
        cell = (d.pixel_size_xy[1] * factor, d.pixel_size_xy[0] * factor)  # (row, col) metres
        dist = np.maximum(ndimage.distance_transform_edt(padded, sampling=cell) - min(cell), 0.0)
        smooth = ndimage.gaussian_filter(dist, (self.sigma_m / cell[0], self.sigma_m / cell[1]), mode="nearest")
        rr = (row[inside] - r0) / factor - 0.5 + 1.0
        cc = (col[inside] - c0) / factor - 0.5 + 1.0
        ds = ndimage.map_coordinates(smooth, [rr, cc], order=3, mode="nearest")
        w[inside] = raised_cosine((ds - self.dead_m) / self.band_m)
        return w


class DemStack:
    """A base :class:`Dem` plus finer layers (finest first), sampled as one blended surface."""

    def __init__(
        self,
        base: Dem,
        layers: list[tuple[Dem, str, str]] | None = None,
        *,
        base_sha256: str = "",
        blend_pixels: float = DEFAULT_BLEND_PIXELS,
    ):
        lo, hi = BLEND_PIXELS_RANGE
        if not (lo <= float(blend_pixels) <= hi):
            raise DemStackConfigError(f"dem.blend_pixels={blend_pixels} must lie in [{lo:g}, {hi:g}] (coarse pixels)")
        self.base = base
        self.base_sha256 = base_sha256
        self.blend_pixels = float(blend_pixels)
        self.layers = [_Layer(dem, sha, entry) for dem, sha, entry in (layers or [])]
        # Bands, coarsest layer first: each one's coarse pixel is that of the first coarser layer whose
        # full-weight core holds the whole layer, else the base's.
        for k in range(len(self.layers) - 1, -1, -1):
            layer = self.layers[k]
            lat, lon = layer.boundary_latlon()
            under = next((c for c in self.layers[k + 1 :] if c.contains_core(lat, lon)), None)
            coarse_px = under.dem.pixel_size_m if under else base.pixel_size_m
            layer.under = under.dem.product if under else base.product
            layer.band_m = self.blend_pixels * coarse_px

    # ------------------------------------------------------------------ Dem interface (the base's)
    # The base DEM must cover every query, so its identity, grid and coordinates are the stack's.
    product = property(lambda self: self.base.product)
    path = property(lambda self: self.base.path)
    pixel_size_m = property(lambda self: self.base.pixel_size_m)
    crs = property(lambda self: self.base.crs)
    transform = property(lambda self: self.base.transform)
    width = property(lambda self: self.base.width)
    height = property(lambda self: self.base.height)
    bounds = property(lambda self: self.base.bounds)

    def latlon_to_pixel(self, lat_deg, lon_deg):
        """Continuous (col, row) in the base DEM."""
        return self.base.latlon_to_pixel(lat_deg, lon_deg)

    def inside(self, col, row):
        """Within the base DEM's pixel-centre hull."""
        return self.base.inside(col, row)

    def coverage(self, lat_deg, lon_deg, spacing_m: float | None = None):
        """(inside, valid) of the base DEM: layers only refine where the base already covers."""
        return self.base.coverage(lat_deg, lon_deg, spacing_m=spacing_m)

    def stack_info(self) -> list[dict]:
        """One entry per layer, finest first: product, path, sha256, pixel, blend band."""
        return [
            {
                "product": layer.dem.product,
                "entry": layer.entry,
                "path": str(layer.dem.path),
                "sha256": layer.sha256,
                "pixel_size_m": layer.dem.pixel_size_m,
                "blend_band_m": layer.band_m,
                "blends_into": layer.under,
            }
            for layer in self.layers
        ]

    def key(self) -> dict:
        """What the stack contributes to a terrain_id: layer contents, order and blending."""
        return {
            "layers": [{"sha256": layer.sha256, "band_m": layer.band_m} for layer in self.layers],
            "blend_pixels": self.blend_pixels,
        }

    def info(self) -> dict:
        return {**self.base.info(), "stack": self.stack_info(), "blend_pixels": self.blend_pixels}

    # ------------------------------------------------------------------ sampling
    def sample(
        self, lat_deg, lon_deg, *, spacing_m: float | None = None, max_nodata_fraction: float = 1.0, what: str = "patch"
    ) -> StackSample:
        """Blended heights (m above the sphere) at (lat, lon): the base DEM's :meth:`Dem.sample`
        (coverage and nodata policy included), refined by every layer where it has data."""
        lat = np.asarray(lat_deg, dtype=np.float64)
        lon = np.asarray(lon_deg, dtype=np.float64)
        lat, lon = np.broadcast_arrays(lat, lon)
        base = self.base.sample(lat, lon, spacing_m=spacing_m, max_nodata_fraction=max_nodata_fraction, what=what)
        heights = base.heights.copy()
        weights = [np.ones(lat.shape)]
        pixels = [self.base.pixel_size_m * base.decimation]
        names = [self.base.product]
        raw = []
        for layer in reversed(self.layers):
            w = layer.weight(lat, lon)
            pix = layer.dem.pixel_size_m
            sel = w > 0.0
            if sel.any():
                fine = layer.dem.sample(
                    lat[sel],
                    lon[sel],
                    spacing_m=spacing_m,
                    max_nodata_fraction=1.0,
                    what=f"{what} in DEM layer {layer.dem.product}",
                )
                heights[sel] += w[sel] * (fine.heights - heights[sel])
                pix = layer.dem.pixel_size_m * fine.decimation
            raw.append((layer.dem.product, w, pix))
        # Final weights: layer k keeps w_k times (1 - w_j) of every finer layer j applied after it.
        remaining = np.ones(lat.shape)
        finals = []
        for name, w, pix in reversed(raw):  # finest first
            finals.append((name, w * remaining, pix))
            remaining = remaining * (1.0 - w)
        weights[0] = remaining
        for name, w, pix in finals:
            names.append(name)
            weights.append(w)
            pixels.append(pix)
        return StackSample(
            heights=heights,
            nodata_fraction=base.nodata_fraction,
            filled_pixels=base.filled_pixels,
            filled_holes=base.filled_holes,
            decimation=base.decimation,
            window=base.window,
            layer_names=names,
            layer_weights=weights,
            layer_pixel_m=pixels,
        )


# --------------------------------------------------------------------------------------------
# Opening from configuration
# --------------------------------------------------------------------------------------------
def open_dem_entry(entry: str, data_dir: str | Path, what: str = "dem.stack entry") -> tuple[Dem, str]:
    """(Dem, sha256) for a registered product id or a DEM file path (anything GDAL reads)."""
    entry = str(entry).strip()
    if not entry:
        raise DemStackConfigError(f"{what} is empty")
    products = load_products()
    if entry in products:
        if products[entry].get("kind") != "dem":
            raise DemStackConfigError(f"{what} {entry!r} is a {products[entry].get('kind')} product, not a DEM")
        p = resolve_product(entry, data_dir)
        return Dem(p, product=entry), cached_sha256(p)
    p = Path(entry).expanduser()
    if not p.exists():
        raise DemStackConfigError(
            f"{what} {entry!r} is neither a registered DEM product "
            f"({', '.join(sorted(k for k, v in products.items() if v.get('kind') == 'dem'))}) "
            "nor an existing file"
        )
    dem = Dem(p, product=p.name)  # one-line DemReadError for a corrupt or unusable file
    return dem, cached_sha256(p)


def open_stack(
    base: Dem, base_sha256: str, entries, data_dir: str | Path, blend_pixels: float = DEFAULT_BLEND_PIXELS
) -> DemStack:
    """A :class:`DemStack` over ``base`` from ``dem.stack`` entries (finest first)."""
    if entries is None:
        entries = []
    if isinstance(entries, str) or not isinstance(entries, (list, tuple)):
        raise DemStackConfigError(f"dem.stack={entries!r} must be a list of DEM product ids or paths")
    layers = []
    for i, entry in enumerate(entries):
        dem, sha = open_dem_entry(str(entry), data_dir, what=f"dem.stack[{i}]")
        if sha == base_sha256:
            continue  # the base itself listed as a layer: nothing to refine
        if any(sha == s for _, s, _ in layers):
            raise DemStackConfigError(f"dem.stack[{i}] {entry!r} is listed twice")
        layers.append((dem, sha, str(entry)))
    for i in range(1, len(layers)):
        if layers[i][0].pixel_size_m < layers[i - 1][0].pixel_size_m:
            raise DemStackConfigError(
                f"dem.stack must list the finest DEM first: {layers[i][2]!r} ({layers[i][0].pixel_size_m:g} m) "
                f"comes after {layers[i - 1][2]!r} ({layers[i - 1][0].pixel_size_m:g} m)"
            )
    return DemStack(base, layers, base_sha256=base_sha256, blend_pixels=blend_pixels)
