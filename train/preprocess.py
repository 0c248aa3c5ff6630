"""The one preprocessing path shared by synthetic I/F renders and real 8-bit crops (docs/preprocessing.md).

    image (float I/F, or 8-bit DN / 255)
      -> resample_box: the sigma ROI box (optionally with its sampling grid rotated), anti-aliased,
         resampled to ``size`` x ``size`` (150 x 150)                       [geometry; cached for renders]
      -> SensorModel.apply (synthetic training/validation images only, seeded; optional)
      -> normalize: robust affine-invariant photometric normalisation into [0, 1]   [photometry]
      -> apply_support: optionally only the box's inscribed disc (``support: disc``)

``normalize`` is invariant to any positive affine map ``a * x + b`` of the input, so I/F values and the
8-bit DN of the same scene under a (linear) camera give the same network input up to quantisation.

numpy, scipy and OpenCV: no torch, no bpy.
"""

from __future__ import annotations

import functools
import io
import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Sequence

import cv2
import numpy as np
from PIL import Image
from scipy import ndimage

from train.errors import DatasetError, TrainError

if TYPE_CHECKING:
    from crater_core.settings import PreprocessSettings, SensorSettings


@dataclass(frozen=True)
class PreprocessConfig:
    """Geometry + photometry of one crop: ``train.preprocess`` plus ``model.input_size`` as ``size``.

    A plain runtime value (what the crop cache key and the LunarNet_ex checkpoint record): the pipeline
    builds it with :meth:`from_settings` from the validated settings, and evaluation from a checkpoint's
    record; it checks nothing itself (the ranges live in :class:`crater_core.settings.PreprocessSettings`).
    The defaults are the paper's values, for the library functions' default arguments."""

    size: int = 150
    antialias: bool = True
    interp_order: int = 1  # 1 = bilinear sampling of the (pre-filtered) window
    max_outside_frac: float = 0.05  # a box may leave its image by at most this fraction of its side
    low_percentile: float = 1.0  # black level
    high_percentile: float = 99.5  # white level, taken over the lit pixels only
    lit_threshold: float = 0.02  # lit = above black + this fraction of (max - black)
    shadow_floor: float = 0.05  # linear values below this (fraction of white) count as shadow -> 0
    gamma: float = 0.5  # output = clip(linear, 0, 1) ** gamma
    support: str = "square"  # square: the whole box; disc: only the box's inscribed disc (rotation-invariant)

    @classmethod
    def from_settings(cls, preprocess: "PreprocessSettings", size: int) -> "PreprocessConfig":
        """The validated ``train.preprocess`` at the network's input size ``size`` (``model.input_size``);
        every range is checked there, once (:class:`crater_core.settings.PreprocessSettings`)."""
        return cls(size=size, **asdict(preprocess))

    def geometry_key(self) -> dict:
        """The settings that determine the cached (pre-photometry) arrays, and the resampler that made them
        (OpenCV's bilinear warp differs from scipy's by up to 1/64 px of the image's slope: a new key)."""
        key = {k: v for k, v in asdict(self).items() if k in ("size", "antialias", "interp_order")}
        return key | {"resampler": "cv2.warpAffine" if self.interp_order == 1 else "scipy.ndimage"}


# ------------------------------------------------------------------------------------------------
# Geometry: box -> size x size
# ------------------------------------------------------------------------------------------------
def box_center_side(box: Sequence[float]) -> tuple[float, float, float, float]:
    """(cu, cv, width, height) of a pixel box (u0, v0, u1, v1)."""
    u0, v0, u1, v1 = (float(b) for b in box)
    if not (u1 > u0 and v1 > v0):
        raise TrainError(f"degenerate pixel box {list(box)}")
    return 0.5 * (u0 + u1), 0.5 * (v0 + v1), u1 - u0, v1 - v0


def rotated_box_extent(box: Sequence[float], rotation_deg: float = 0.0) -> tuple[float, float, float, float]:
    """Axis-aligned bounds (u0, v0, u1, v1) of the box's sampling grid after rotation about its centre."""
    cu, cv, w, h = box_center_side(box)
    t = math.radians(rotation_deg)
    hu = 0.5 * (abs(w * math.cos(t)) + abs(h * math.sin(t)))
    hv = 0.5 * (abs(w * math.sin(t)) + abs(h * math.cos(t)))
    return cu - hu, cv - hv, cu + hu, cv + hv


def outside_fraction(box: Sequence[float], shape: tuple[int, int], rotation_deg: float = 0.0) -> float:
    """How far (as a fraction of the box side) the (rotated) box leaves an image of ``shape`` (H, W)."""
    u0, v0, u1, v1 = rotated_box_extent(box, rotation_deg)
    _, _, w, h = box_center_side(box)
    H, W = shape
    over = max(0.0, -u0, -v0, u1 - W, v1 - H)
    return over / min(w, h)


def resample_box(
    image: np.ndarray,
    box: Sequence[float],
    size: int,
    rotation_deg: float = 0.0,
    antialias: bool = True,
    order: int = 1,
) -> np.ndarray:
    """Sample the pixel box (u0, v0, u1, v1) of a 2-D ``image`` onto a ``size`` x ``size`` grid.

    Pixel coordinates: u right, v down, origin at the top-left *corner* of the image (pixel (i, j)
    covers [j, j+1) x [i, i+1)), the convention of the manifest's ``sigma_boxes`` and of the mosaic.
    ``rotation_deg`` rotates the sampling grid about the box centre (counter-clockwise on screen, so
    the crop's content appears turned clockwise by that angle); a rotated crop has no empty corners as
    long as the rotated box stays inside the image. When the
    box side exceeds ``size`` pixels the window is first Gaussian-filtered (sigma = (scale - 1) / 2,
    scikit-image's anti-aliasing rule). Samples that fall outside the image take the nearest edge value.
    Returns float32 (size, size). A rotated box is the special case of :func:`resample_affine`.
    """
    cu, cv, w, h = box_center_side(box)
    return resample_affine(image, (cu, cv), box_axes(w, h, rotation_deg), size, antialias, order)


def cached_crop(
    image: np.ndarray, box: Sequence[float], pp: PreprocessConfig, where: str = "image", sigma: float | None = None
) -> np.ndarray:
    """The geometric step alone, unrotated, as the crop cache stores it (train/data.py) and
    ``crater-synth export --shape crop`` writes it: the sigma ``box`` of a 2-D ``image`` resampled by
    :func:`resample_box` to ``pp.size`` x ``pp.size`` float32. A box that leaves the image by more than
    ``pp.max_outside_frac`` of its side is a :class:`DatasetError` naming ``where`` and ``sigma``."""
    if outside_fraction(box, image.shape) > pp.max_outside_frac:
        raise DatasetError(
            f"{where}: sigma={sigma} box {list(box)} leaves the {image.shape[1]}x{image.shape[0]} "
            f"image by more than {pp.max_outside_frac:.0%} of its side"
        )
    return resample_box(image, box, pp.size, 0.0, pp.antialias, pp.interp_order)


def box_axes(w: float, h: float, rotation_deg: float = 0.0) -> np.ndarray:
    """The 2x2 sampling axes of a ``w`` x ``h`` box whose grid is turned by ``rotation_deg``
    (counter-clockwise on screen; v points down): column 0 is the image-pixel vector spanned by the
    crop's whole width, column 1 by its whole height."""
    t = math.radians(rotation_deg)
    ct, st = math.cos(t), math.sin(t)
    # u' = u cos + v sin, v' = -u sin + v cos.
    return np.array([[ct * w, st * h], [-st * w, ct * h]], dtype=np.float64)


def axes_extent(center: Sequence[float], axes) -> tuple[float, float, float, float]:
    """Axis-aligned bounds (u0, v0, u1, v1) of the parallelogram ``center + axes @ [-1/2, 1/2]^2``."""
    a = np.asarray(axes, dtype=np.float64).reshape(2, 2)
    hu = 0.5 * (abs(a[0, 0]) + abs(a[0, 1]))
    hv = 0.5 * (abs(a[1, 0]) + abs(a[1, 1]))
    cu, cv = float(center[0]), float(center[1])
    return cu - hu, cv - hv, cu + hu, cv + hv


def resample_affine(
    image: np.ndarray,
    center: Sequence[float],
    axes,
    size: int,
    antialias: bool = True,
    order: int = 1,
) -> np.ndarray:
    """Sample the parallelogram ``center + axes @ (s, t)``, s, t in [-1/2, 1/2], of a 2-D ``image``
    onto a ``size`` x ``size`` grid (output column <-> s, row <-> t).

    ``axes`` (2x2, image pixels): column 0 is the vector the crop's width spans, column 1 its height;
    a rotated square box is :func:`box_axes`, a real frame's crop is the local linear map of the
    georeference times that (train/realframes.py). Anti-aliasing as in :func:`resample_box`, with the
    footprint of one output pixel along each image axis (:func:`crop_window`). Bilinear (``order`` 1) is
    OpenCV's warp; nearest (0) and cubic spline (3) are scipy's (:func:`spline_sample`: OpenCV has no warp
    of those kernels). Samples outside the image take the nearest edge value. Returns float32 (size, size).
    """
    win, to_window = crop_window(image, center, axes, size, antialias)
    if order != 1:
        return spline_sample(win, to_window, size, order)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(win, to_window, (size, size), flags=flags, borderMode=cv2.BORDER_REPLICATE)


def crop_window(image: np.ndarray, center: Sequence[float], axes, size: int, antialias: bool = True, blur=None):
    """(window, to_window) of :func:`resample_affine`: the float32 window of ``image`` holding the
    parallelogram plus the filter and interpolation support (beyond the image: its edge values),
    Gaussian-filtered when one output pixel spans more than one image pixel (sigma = (scale - 1) / 2
    along each image axis), and the (2, 3) affine map from an output pixel (x, y, 1) to window (col, row)
    array coordinates. ``blur(window, sigma_u, sigma_v)`` replaces OpenCV's Gaussian (the benchmark's
    reference passes scipy's)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise TrainError(f"resample_box needs a 2-D image, got shape {img.shape}")
    a = np.asarray(axes, dtype=np.float64).reshape(2, 2)
    if not (np.all(np.isfinite(a)) and abs(np.linalg.det(a)) > 0):
        raise TrainError(f"degenerate sampling axes {a.tolist()}")
    cu, cv = float(center[0]), float(center[1])
    # Footprint of one output pixel along the image's u and v axes.
    scale_u, scale_v = math.hypot(a[0, 0], a[0, 1]) / size, math.hypot(a[1, 0], a[1, 1]) / size
    aa_u = max(0.0, (scale_u - 1.0) / 2.0) if antialias else 0.0
    aa_v = max(0.0, (scale_v - 1.0) / 2.0) if antialias else 0.0
    # Window holding the grid plus the filter and interpolation support.
    e0u, e0v, e1u, e1v = axes_extent((cu, cv), a)
    pad = int(math.ceil(4.0 * max(aa_u, aa_v))) + 3
    H, W = img.shape
    r0, r1 = int(math.floor(e0v)) - pad, int(math.ceil(e1v)) + pad
    c0, c1 = int(math.floor(e0u)) - pad, int(math.ceil(e1u)) + pad
    rr0, rr1, cc0, cc1 = max(r0, 0), min(r1, H), max(c0, 0), min(c1, W)
    if rr1 <= rr0 or cc1 <= cc0:
        raise TrainError(
            f"sampling box {[round(e, 2) for e in (e0u, e0v, e1u, e1v)]} lies entirely outside the {W}x{H} image"
        )
    win = img[rr0:rr1, cc0:cc1].astype(np.float32, copy=True)
    if (rr0, rr1, cc0, cc1) != (r0, r1, c0, c1):
        win = np.pad(win, ((rr0 - r0, r1 - rr1), (cc0 - c0, c1 - cc1)), mode="edge")
    if (aa_u > 0 or aa_v > 0) and blur is not None:
        win = blur(win, aa_u, aa_v)
    elif aa_u > 0 or aa_v > 0:
        # scipy's gaussian_filter(sigma=(aa_v, aa_u), mode="nearest", truncate=4.0), by OpenCV's separable filter.
        kx, ky = gaussian_kernel(aa_u), gaussian_kernel(aa_v)
        win = cv2.sepFilter2D(win, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REPLICATE)
    # Output pixel (col x, row y) -> its centre in crop-normalised coordinates (s, t) = ((x, y) + 0.5) / size
    # - 0.5 -> the image's continuous (u, v) through the axes -> window array index (pixel centres at i + 0.5).
    lin = a / size
    shift = np.array([cu - 0.5 - c0, cv - 0.5 - r0]) + lin @ np.full(2, 0.5 - 0.5 * size)
    return win, np.column_stack([lin, shift])


def gaussian_kernel(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """The normalised 1-D Gaussian of ``sigma`` px cut at ``truncate`` sigma, scipy's ``gaussian_filter``
    kernel (radius int(truncate sigma + 0.5)); [1] for sigma 0."""
    radius = int(truncate * sigma + 0.5)
    if radius == 0:
        return np.ones(1)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    phi = np.exp(-0.5 * (x / sigma) ** 2)
    return phi / phi.sum()


def spline_sample(win: np.ndarray, to_window: np.ndarray, size: int, order: int) -> np.ndarray:
    """scipy's spline interpolation of order ``order`` of ``win`` at the ``size`` x ``size`` output grid
    mapped by ``to_window`` (:func:`crop_window`); outside the window, its nearest edge value. float32."""
    x, y = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64), indexing="xy")
    cols = to_window[0, 0] * x + to_window[0, 1] * y + to_window[0, 2]
    rows = to_window[1, 0] * x + to_window[1, 1] * y + to_window[1, 2]
    out = ndimage.map_coordinates(win, [rows, cols], order=order, mode="nearest", prefilter=order > 1)
    return out.astype(np.float32)


# ------------------------------------------------------------------------------------------------
# Photometry
# ------------------------------------------------------------------------------------------------
def normalize(image: np.ndarray, pp: PreprocessConfig = PreprocessConfig()) -> np.ndarray:
    """Robust, affine-invariant photometric normalisation to float32 in [0, 1].

    black = ``low_percentile`` of all pixels; lit = pixels above black + ``lit_threshold`` x
    (max - black); white = ``high_percentile`` of the lit pixels (falls back to the max when fewer
    than 16 pixels are lit); linear = (x - black) / (white - black); a dead zone removes what is
    indistinguishable from shadow (JPEG blocks and noise of the real 8-bit frames, sensor noise of the
    synthetic ones): out = clip((linear - shadow_floor) / (1 - shadow_floor), 0, 1) ** gamma. An image
    with no contrast at all (fully shadowed) becomes all zeros.
    """
    x = np.asarray(image, dtype=np.float32)
    flat = x.ravel()
    if not np.all(np.isfinite(flat)):
        flat = np.nan_to_num(flat, nan=0.0, posinf=0.0, neginf=0.0)
        x = flat.reshape(x.shape)
    black = float(np.percentile(flat, pp.low_percentile))
    top = float(flat.max())
    span = top - black
    if not span > 1e-12 * max(1.0, abs(top)):
        return np.zeros(x.shape, dtype=np.float32)
    lit = flat[flat > black + pp.lit_threshold * span]
    white = float(np.percentile(lit, pp.high_percentile)) if lit.size >= 16 else top
    if not white > black:
        white = top
    y = (x - black) / (white - black)
    if pp.shadow_floor > 0:
        y = (y - pp.shadow_floor) / (1.0 - pp.shadow_floor)
    y = np.clip(y, 0.0, 1.0)
    if pp.gamma != 1.0:
        y = y**pp.gamma
    return y.astype(np.float32)


def preprocess_crop(
    image: np.ndarray,
    box: Sequence[float],
    pp: PreprocessConfig = PreprocessConfig(),
    rotation_deg: float = 0.0,
    sensor: "SensorModel | None" = None,
    rng: np.random.Generator | None = None,
    box_side_m: float | None = None,
    axes=None,
) -> np.ndarray:
    """The whole path for one crop: resample_box -> (sensor) -> normalize. ``image`` may be float I/F
    or integer DN (8-bit real frames); both go through exactly the same steps. ``box_side_m`` (the
    crop's ground width) lets a sensor with ``gsd_m`` sample it on the real product's grid. ``axes``
    (2x2, optional) replaces the box's side and rotation by a general sampling parallelogram centred
    on the box centre (:func:`resample_affine`; a georeferenced real frame's crop)."""
    a = np.asarray(image)
    if axes is None:
        crop = resample_box(a, box, pp.size, rotation_deg, pp.antialias, pp.interp_order)
    else:
        cu, cv, _, _ = box_center_side(box)
        crop = resample_affine(a, (cu, cv), axes, pp.size, pp.antialias, pp.interp_order)
    if np.issubdtype(a.dtype, np.integer):  # DN -> [0, 1] (a pure scale; only the window is converted)
        crop = crop / np.float32(np.iinfo(a.dtype).max)
    if sensor is not None and sensor.enabled:
        crop = sensor.apply(crop, rng if rng is not None else np.random.default_rng(0), box_side_m=box_side_m)
    return apply_support(normalize(crop, pp), pp)


@functools.lru_cache(maxsize=8)
def _disc(size: int) -> np.ndarray:
    c = (np.arange(size, dtype=np.float32) + 0.5) - size / 2.0
    return (c[None, :] ** 2 + c[:, None] ** 2 <= (size / 2.0) ** 2).astype(np.float32)


def apply_support(y: np.ndarray, pp: PreprocessConfig = PreprocessConfig()) -> np.ndarray:
    """The last step for every crop, real or synthetic: with ``support="disc"`` everything outside the
    box's inscribed disc is set to 0 (shadow). A disc is the one support that any rotation of the
    camera about its boresight maps onto itself, so a training crop can be rotated by any angle
    without empty corners, exactly as the real crops are (docs/preprocessing.md)."""
    if pp.support == "square":
        return y
    return (y * _disc(y.shape[-1])).astype(np.float32, copy=False)


def rotate_crop(y: np.ndarray, angle_deg: float, shift_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``y`` turned by ``angle_deg`` about its centre and moved by ``shift_px`` (du right, dv down), in
    one bilinear resampling; what leaves the square is dropped, what enters it is 0. Used on
    disc-support crops, whose content any rotation keeps inside the box (a shift brings in a thin
    crescent of 0 at the disc's edge). ``y`` is one (H, W) crop or a stack (..., H, W), each turned
    the same way in one call."""
    y = np.asarray(y, dtype=np.float32)
    a = math.radians(float(angle_deg))
    h, w = y.shape[-2:]
    # Output (x, y) -> input (x, y): rotate about the centre (as ndimage.rotate does) after undoing the shift.
    m = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    c = (np.array([w, h], dtype=np.float64) - 1.0) / 2.0
    to_input = np.column_stack([m, c - m @ (c + np.asarray(shift_px, dtype=np.float64))])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    # A sample from beyond the input's outermost pixel centres is 0 (not a blend of the edge and 0).
    xi, yi = np.tensordot(to_input, np.stack([*np.meshgrid(np.arange(w), np.arange(h)), np.ones((h, w))]), 1)
    outside = (xi < 0.0) | (xi > w - 1.0) | (yi < 0.0) | (yi > h - 1.0)

    def turn(img: np.ndarray) -> np.ndarray:
        out = cv2.warpAffine(img, to_input, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        out[outside] = 0.0
        return out

    if y.ndim == 2:
        return turn(y)
    stack = y.reshape((-1, h, w))
    return np.stack([turn(img) for img in stack]).reshape(y.shape)


# ------------------------------------------------------------------------------------------------
# Optional sensor model for synthetic images (configs/sensor)
# ------------------------------------------------------------------------------------------------
MOSAIC_BLENDS = ("max", "patches")


def mosaic_composite(
    frames: Sequence[np.ndarray], rng: np.random.Generator, blend: str = "max", patches: int = 6
) -> np.ndarray:
    """One image assembled from renders of the same camera pose under different suns, as the real
    polar mosaic is assembled from frames taken over months (docs/preprocessing.md, "Mosaic").

    ``max``: per pixel, the brightest frame (a mosaic that keeps the best-lit observation of each
    place). ``patches``: the image is cut into ``patches`` Voronoi cells around uniform random seeds
    and each cell comes from one randomly chosen frame (seams between frames, as in a mosaic).
    All frames must have the same shape; one frame is returned unchanged (as float32)."""
    stack = np.stack([np.asarray(f, dtype=np.float32) for f in frames])
    if len(stack) == 1:
        return stack[0]
    if blend == "max":
        return stack.max(axis=0)
    if blend != "patches":
        raise TrainError(f"mosaic blend {blend!r}: choose one of {', '.join(MOSAIC_BLENDS)}")
    h, w = stack.shape[1:]
    seeds = rng.uniform(0.0, 1.0, size=(int(patches), 2)) * np.array([h, w])
    owner = rng.integers(len(stack), size=int(patches))
    yy, xx = np.mgrid[0:h, 0:w]
    d2 = (yy[None] - seeds[:, 0, None, None]) ** 2 + (xx[None] - seeds[:, 1, None, None]) ** 2
    frame_of_pixel = owner[np.argmin(d2, axis=0)]
    return np.take_along_axis(stack, frame_of_pixel[None], axis=0)[0]


@dataclass(frozen=True)
class SensorModel:
    """Seeded camera model applied to a resampled synthetic I/F crop before normalisation.

    Sampling first, in one of two ways:
    - ``gsd_m`` set (the real test product's ground sample distance, e.g. 400 m for the LROC WAC
      mosaic): the crop is area-averaged onto the grid the real sensor would have, native_px =
      box side in metres / gsd_m (times U[1 - gsd_jitter, 1 + gsd_jitter]), the PSF, exposure, noise,
      quantisation and JPEG compression (``jpeg_quality``) act on that grid, and it is brought back to
      the crop size with the same bilinear up-sampling the real crops get (``resample_box``). A crop
      whose native grid is at least as fine as the crop is left at the crop size.
    - otherwise an effective-resolution jitter (down-sample to r x r, r ~ U[resolution_min_px, size],
      with probability ``resolution_prob``, and back).
    Then: Gaussian PSF (``psf_sigma_px``, in pixels of the sampling grid), exposure (automatic: the
    image's white level -- the 99.5th percentile of its lit pixels -- lands at a random fraction
    ``exposure_white_frac`` of full scale, as a camera exposing for the scene; or fixed:
    ``full_well_if``), gain jitter, shot noise (photo-electrons; normal approximation of the Poisson
    law), read noise (DN), quantisation to ``quantize_bits`` with saturation at ``full_well_if`` x
    gain, and optionally JPEG compression. Returns DN / full scale (float32).

    ``mosaic_frames`` > 1 asks the training dataset to composite that many renders of the same camera
    pose under different suns (:func:`mosaic_composite`) before :meth:`apply`; it needs several
    renders, so the dataset (train/data.py), not this class, does it.

    Built by :meth:`from_settings` from the validated ``sensor`` group; it checks nothing itself (the
    ranges live in :class:`crater_core.settings.SensorSettings`).
    """

    enabled: bool = True
    psf_sigma_px: float = 0.7
    auto_exposure: bool = True  # exposure per image: white level -> U[exposure_white_frac] x full scale
    exposure_white_frac: tuple = (0.6, 1.05)
    full_well_if: float = 0.25  # fixed exposure (auto_exposure=false): this I/F saturates at gain 1
    photons_at_full_well: float = 4000.0
    read_noise_dn: float = 1.0
    gain_jitter: float = 0.15
    quantize_bits: int = 8
    resolution_min_px: int = 0  # 0 = no resolution jitter
    resolution_prob: float = 0.5  # probability of applying the resolution jitter
    gsd_m: float | None = None  # real sensor's ground sample distance (m/px); None = jitter instead
    gsd_jitter: float = 0.0  # relative jitter of the native grid size
    jpeg_quality: int | None = None  # JPEG quality of the real product (None = no JPEG)
    mosaic_frames: int = 1  # renders of one camera pose (different suns) composited per image
    mosaic_blend: str = "max"  # how they are composited: max (per pixel) or patches (Voronoi cells)
    mosaic_patches: int = 6  # number of cells for mosaic_blend=patches

    @classmethod
    def from_settings(cls, sensor: "SensorSettings") -> "SensorModel":
        """The camera of the validated ``sensor`` group (ranges checked there, once:
        :class:`crater_core.settings.SensorSettings`)."""
        return cls(**asdict(sensor))

    def apply(self, image_if: np.ndarray, rng: np.random.Generator, box_side_m: float | None = None) -> np.ndarray:
        """The camera applied to one square I/F crop; ``box_side_m`` (the crop's ground width, needed
        with ``gsd_m``) sets the native sampling grid. Returns DN / full scale at the crop's size."""
        x = np.asarray(image_if, dtype=np.float32)
        n = x.shape[0]
        native = n
        if self.gsd_m is not None and box_side_m is not None:
            jitter = rng.uniform(1.0 - self.gsd_jitter, 1.0 + self.gsd_jitter) if self.gsd_jitter else 1.0
            native = int(np.clip(round(box_side_m / self.gsd_m * jitter), 4, n))
        elif self.resolution_min_px and self.resolution_min_px < n and rng.random() < self.resolution_prob:
            native = int(rng.integers(self.resolution_min_px, n + 1))
        if native < n:  # area-average onto the sensor's grid (anti-aliased resampling)
            x = resample_box(x, (0, 0, x.shape[1], x.shape[0]), native, antialias=True, order=1)
        if self.psf_sigma_px > 0:
            x = ndimage.gaussian_filter(x, self.psf_sigma_px, mode="nearest")
        x = self._expose(x, rng)
        if self.jpeg_quality is not None:
            x = jpeg_roundtrip(x, int(self.jpeg_quality))
        if native < n:  # back to the crop size, as the real crops are up-sampled
            x = resample_box(x, (0, 0, native, native), n, antialias=False, order=1)
        return x.astype(np.float32)

    def _expose(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Exposure, gain, shot and read noise, quantisation: I/F -> DN / full scale."""
        gain = 1.0 + rng.uniform(-self.gain_jitter, self.gain_jitter) if self.gain_jitter else 1.0
        full = float(2 ** int(self.quantize_bits) - 1)
        dn_per_e = full / self.photons_at_full_well
        full_well_if = self.full_well_if
        if self.auto_exposure:
            top = float(x.max())
            if top <= 0:
                full_well_if = 1.0
            else:
                lit = x[x > 0.02 * top]
                white = float(np.percentile(lit, 99.5)) if lit.size >= 16 else top
                full_well_if = white / rng.uniform(*self.exposure_white_frac)
        electrons = np.clip(x, 0.0, None) * np.float32(self.photons_at_full_well * gain / full_well_if)
        # Shot noise (Poisson, variance = mean) and read noise in one Gaussian draw: the normal
        # approximation of the Poisson law is accurate above ~20 e-, and below that the read noise
        # and the quantisation step (4000 e- / 255 = 16 e- per DN) dominate anyway.
        sd = np.sqrt(electrons * np.float32(dn_per_e**2) + np.float32(self.read_noise_dn**2))
        dn = electrons * np.float32(dn_per_e) + sd * rng.standard_normal(size=x.shape, dtype=np.float32)
        dn = np.clip(np.rint(dn), 0.0, full)
        return (dn / full).astype(np.float32)


def jpeg_roundtrip(x01: np.ndarray, quality: int) -> np.ndarray:
    """Baseline JPEG encode/decode (libjpeg through Pillow, 4:4:4 grey) of an image in [0, 1] already
    quantised to 8 bits: the real product's compression artefacts (block edges, ringing)."""
    img = Image.fromarray(np.clip(np.rint(np.asarray(x01) * 255.0), 0, 255).astype(np.uint8), mode="L")
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    return np.asarray(Image.open(buf), dtype=np.float32) / 255.0
