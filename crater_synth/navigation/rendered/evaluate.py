"""Navigation metrics on rendered frames with exact truth (``crater-synth nav-frames-eval DIR``).

The same pipeline and metrics as ``crater-synth nav-eval`` on real mosaic windows
(:mod:`..windows.evaluate`), for the perspective frames of ``crater-synth nav-frames``:

- **Detection**: :func:`..detectors.classical.detect` on the I/F channel, with the settings of a preset
  (``nav/preset``, configs/nav/preset/; "synthetic", the classical detector's settings chosen on rendered frames;
  "learned"; "real-window": the real windows' settings unchanged), or no detector: the default
  "appearance" preset searches for the map's landmarks by their predicted appearance (:mod:`..fix.appearance`).
  The light direction in the image is given (the lander knows its attitude and the ephemeris): the Sun's
  travel direction, projected on the image plane. The "synthetic" preset searches only the radii the map
  can use in the frame (:func:`map_scales`: from the ground sample, as a lander knowing its altitude would).
- **Truth**: the frame's labels (every landmark whose rim centre projects inside the frame, with its
  projected rim ellipse; :mod:`.frames`), less those whose rim is mostly hidden behind nearer
  relief (:data:`.labels.HIDDEN_RIM_MAX`): they are not counted as misses, nor a detection on
  them as false. A detection matches a label when its centre is within 0.25 D of the ellipse centre
  and its radius within 25 % of the ellipse's semi-major axis.
- **Prior**: the true camera moved ``PRIOR_OFFSET_KM`` horizontally in a seeded random direction;
  the attitude is the true one (the same assumption as nav-eval's exact prior heading and scale).
- **Identification**: map landmarks >= ``min_landmark_km`` (those a finer DEM layer added: from
  ``LAYER_LANDMARK_MIN_PX`` px) projected with the prior pose; putative pairs within the prior's
  uncertainty (``prior_sigma_km`` / ground sample + r/4 px) and radius ratio within ``radius_ratio``
  (:class:`..fix.solve.FixParams`, the values chosen on real validation windows).
- **Fix** (``nav.frames.solver``): ``position`` (default): the camera centre with the prior's (true) attitude,
  :func:`..fix.solve.ransac_position` (least squares on the rays through the landmarks' 3-D rim-centre
  points, minimal sets of 2), corrected for the perspective offset of the rim ellipses' centres
  (:func:`..fix.refine.ellipse_centre_fix`); ``pnp``: the full pose, :func:`..fix.solve.ransac_pnp`. One pair per
  detection and landmark; "no fix" when fewer than ``min_inliers`` distinct landmarks agree, when a
  disjoint rival set nearly as large agrees (the ambiguity test; known attitude) or when their RMS
  exceeds ``max_rms_px``. Presets with ``refine`` then register each fix landmark's predicted
  appearance on the frame and solve again (:mod:`..fix.refine`; a 6-DOF fix with ``refine_pnp``, attitude
  too). A frame with fewer than ``min_inliers`` landmarks in view is flagged and summarised apart. The
  error is the 3-D distance between the fixed and the true camera centre (horizontal part too); a fix is
  false beyond ``FALSE_FIX_KM``.
- **Options**: terrain patches where the craters give no fix (:func:`with_patch_fallback`), each frame's
  prior from its trajectory's last fix (:mod:`..fix.sequence`).

Metrics are :func:`..protocol.summarise`'s (one definition for real and rendered frames). The command
is :mod:`.cli`.

Length: one stage, a rendered frame's navigation scored against its labels: the frame's camera, the
identification, both fixes with their refinement, the patch fallback and the loop over a directory share
one frame geometry and one row format, so they are kept together.
"""

from __future__ import annotations

import dataclasses
import math
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from crater_core import exr, geometry
from crater_core.progress import Progress
from crater_core.settings_nav import AppearanceSettings, DetectorSettings, FramesSettings
from crater_synth.navigation.detectors.classical import ClassicalSettings, Detection, detect
from crater_synth.navigation.fix.appearance import appearance_detections
from crater_synth.navigation.fix.patches import PatchParams, patch_landmarks
from crater_synth.navigation.fix.pose import (
    attitude_difference_deg,
    pose_sigma_horizontal_m,
    position_sigma_horizontal_m,
    project_pinhole,
    rodrigues,
)
from crater_synth.navigation.fix.refine import RefineParams, Refiner, ellipse_centre_fix, lander_dem, rim_ellipses
from crater_synth.navigation.fix.sequence import SequenceParams, last_fix, propagated_prior
from crater_synth.navigation.fix.solve import FixParams, ransac_pnp, ransac_position
from crater_synth.navigation.georef import FrameError, pole_of
from crater_synth.navigation.map.dem_error import DemErrorParams, PerturbedDem
from crater_synth.navigation.map.landmarks import load_default_map, positions_mc
from crater_synth.navigation.protocol import (
    HEADLINE_MIN_D_KM,
    HEADLINE_MIN_LANDMARKS,
    MATCH_CENTRE_D,
    MATCH_DIAMETER,
    PRIOR_OFFSET_KM,
    rendered_summary,
)
from crater_synth.navigation.rendered.labels import hidden, labelled_rows
from crater_synth.navigation.rendered.sunlight import light_direction, row_to_sun
from crater_synth.navigation.settings import map_scales

NOT_ENOUGH_LANDMARKS = "not enough landmarks in view"
# A landmark a finer DEM layer added to the map (below the map's own min_landmark_km) is used where the frame
# resolves it as the real windows resolve their smallest: D >= 25 px (10 km at their 400 m/px).
LAYER_LANDMARK_MIN_PX = 25.0
PNP_INLIER_PX = FramesSettings().inlier_px  # the pinhole fix's inlier tolerance without a preset (nav.frames)


def usable(landmark, gsd_m: float, fparams: FixParams) -> bool:
    """Whether a frame of ground sample ``gsd_m`` uses ``landmark``: one of the map's own DEM from
    ``fparams.min_landmark_km``, one of a finer DEM layer (``dem_product`` set) from
    :data:`LAYER_LANDMARK_MIN_PX` frame pixels."""
    if not landmark.dem_product:
        return landmark.diameter_km >= fparams.min_landmark_km
    return landmark.diameter_km * 1000.0 >= LAYER_LANDMARK_MIN_PX * gsd_m


def cv_camera(rotation: np.ndarray, width: int, fov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(world -> camera rotation in the computer-vision convention of :func:`.fix.project_pinhole`, K)
    of a Blender-convention camera (columns right, up, back)."""
    right, up, back = rotation[:, 0], rotation[:, 1], rotation[:, 2]
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    k = np.array([[f, 0.0, width / 2.0], [0.0, f, width / 2.0], [0.0, 0.0, 1.0]])
    return np.stack([right, -up, -back]), k


def true_camera(row: dict) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cv_camera` of a frame's true camera (its manifest ``row``'s rotation, width and field of view)."""
    rotation = np.array(row["camera_enu"]["rotation"], dtype=np.float64)
    return cv_camera(rotation, int(row["pose"]["width_px"]), float(row["pose"]["fov_deg"]))


def match_pixels(dets, labels: list[dict]) -> dict[int, int]:
    """One-to-one matches detection index -> label index, nearest first (0.25 D, 25 % in radius)."""
    if not dets or not labels:
        return {}
    cu = np.array([lb["ellipse"]["cu"] for lb in labels])
    cv = np.array([lb["ellipse"]["cv"] for lb in labels])
    r = np.array([lb["ellipse"]["a"] for lb in labels])
    du = np.array([d.u for d in dets])[:, None] - cu[None, :]
    dv = np.array([d.v for d in dets])[:, None] - cv[None, :]
    dist = np.hypot(du, dv) / (2.0 * r[None, :])
    dr = np.array([d.r for d in dets])[:, None] / r[None, :]
    ok = (dist <= MATCH_CENTRE_D) & (np.abs(dr - 1.0) <= MATCH_DIAMETER)
    out: dict[int, int] = {}
    used: set[int] = set()
    for i, j in sorted(zip(*np.nonzero(ok)), key=lambda p: dist[p]):
        if int(i) not in out and int(j) not in used:
            out[int(i)] = int(j)
            used.add(int(j))
    return out


def prior_centre(row: dict, seed: int, offset_km: float = PRIOR_OFFSET_KM) -> np.ndarray:
    """The true camera centre (frame ENU) moved ``offset_km`` horizontally in a seeded direction."""
    rng = np.random.default_rng([seed, zlib.crc32(f"{row['trajectory']}:{row['index']}".encode())])
    phi = rng.uniform(0.0, 2.0 * math.pi)
    c = np.array(row["camera_enu"]["position_m"], dtype=np.float64)
    return c + offset_km * 1000.0 * np.array([math.cos(phi), math.sin(phi), 0.0])


def believed_rotation(row: dict, seed: int, attitude_error_deg: float) -> np.ndarray:
    """The camera rotation the lander believes: the true one turned by ``attitude_error_deg`` about a seeded
    axis (the true one when 0)."""
    rot = np.array(row["camera_enu"]["rotation"], dtype=np.float64)
    if attitude_error_deg:
        axis = np.random.default_rng([seed, 7, zlib.crc32(row["rel_path"].encode())]).normal(size=3)
        rot = rodrigues(axis / np.linalg.norm(axis) * math.radians(attitude_error_deg)) @ rot
    return rot


@dataclasses.dataclass(frozen=True)
class FrameRun:
    """The settings every frame of a run is navigated with (:func:`frame_run` builds them from ``nav``):
    ``dparams`` the detector's (unused by the appearance search), ``fparams`` the identification's and the
    fix's; ``seed`` of the prior offsets and attitude errors; ``method`` the fix (``position``: the camera
    centre with the believed attitude; ``pnp``: the 6-DOF pose); ``scales_from_map``: the detector searches
    only the radii of the map landmarks the prior predicts in the frame (:func:`map_scales`); ``inlier_px``:
    the fix's reprojection inlier tolerance; ``refine``: fixes refined by appearance (the run opens the
    lander's DEM); ``appearance``: no detector, the landmarks are searched for by their predicted appearance
    (:mod:`.appearance`, the refiner's DEM); ``attitude_error_deg``: the pipeline works with the attitude
    turned by this angle about a seeded axis (the lander's attitude error; the image and the truth are the
    frame's); ``prior_offset_km``: how far the prior is from the true camera (horizontally, seeded
    direction); ``refine_pnp``: a 6-DOF fix is refined too, weighted towards the believed attitude by its
    1-sigma ``attitude_sigma_deg`` when > 0; ``pnp_attitude_sigma_deg`` > 0: the 6-DOF fix itself takes the
    believed attitude as a measurement of that 1-sigma (:func:`.fix.solve.ransac_pnp`)."""

    dparams: DetectorSettings = dataclasses.field(default_factory=ClassicalSettings)
    fparams: FixParams = dataclasses.field(default_factory=FixParams)
    seed: int = 0
    method: str = "position"
    scales_from_map: bool = False
    inlier_px: float = PNP_INLIER_PX
    refine: bool = False
    appearance: AppearanceSettings | None = None
    attitude_error_deg: float = 0.0
    prior_offset_km: float = PRIOR_OFFSET_KM
    refine_pnp: bool = False
    attitude_sigma_deg: float = 0.0
    pnp_attitude_sigma_deg: float = 0.0


def frame_run(nav, **kw) -> FrameRun:
    """The :class:`FrameRun` of the composed ``nav`` settings (:func:`.settings.compose_nav`): its detector (or
    the appearance search, with the classical defaults as unused detector settings), fix and ``nav.frames``;
    ``kw`` replaces any field (the seed, the attitude error, ...)."""
    appearance = nav.detector if nav.appearance else None
    run = FrameRun(
        dparams=ClassicalSettings() if appearance else nav.detector,
        fparams=nav.fix,
        method=nav.frames.solver,
        scales_from_map=nav.frames.scales_from_map,
        inlier_px=nav.frames.inlier_px,
        refine=nav.frames.refine,
        appearance=appearance,
    )
    return dataclasses.replace(run, **kw)


@dataclasses.dataclass(frozen=True)
class FrameView:
    """One frame as the lander sees it under the prior: the believed camera (``r_wc``, ``k``) at the prior
    centre ``c_prior``, the true centre ``c_true``, and the candidate landmarks ``cand`` with their points
    (frame ENU) ``pts``, predicted pixels ``uv``, radii ``r_pred`` (px) and whether each is ``inside``."""

    row: dict
    origin: tuple
    r_wc: np.ndarray
    k: np.ndarray
    c_true: np.ndarray
    c_prior: np.ndarray
    width: int
    fov: float
    gsd: float
    light: float
    cand: list
    pts: np.ndarray
    uv: np.ndarray
    r_pred: np.ndarray
    inside: np.ndarray


def frame_view(row: dict, landmarks, run: FrameRun, prior_enu=None, candidates=None) -> FrameView:
    """The frame's :class:`FrameView`: the prior (``prior_enu``, else the true camera moved by
    ``run.prior_offset_km``) and the map landmarks it predicts in the frame (``candidates`` instead of the
    usable map landmarks when given)."""
    lat0, lon0 = row["frame_origin"]["lat"], row["frame_origin"]["lon"]
    rot = believed_rotation(row, run.seed, run.attitude_error_deg)
    width, fov, gsd = int(row["pose"]["width_px"]), float(row["pose"]["fov_deg"]), float(row["ground_sample_m"])
    to_sun = row_to_sun(row)
    r_wc, k = cv_camera(rot, width, fov)
    c_prior = prior_centre(row, run.seed, run.prior_offset_km) if prior_enu is None else np.asarray(prior_enu, float)
    cand = [lm for lm in landmarks if usable(lm, gsd, run.fparams)] if candidates is None else list(candidates)
    pts = geometry.mc_to_enu(positions_mc(cand), lat0, lon0) if cand else np.zeros((0, 3))
    depth = (pts - c_prior) @ r_wc[2]
    front = depth > 0
    uv = np.full((len(pts), 2), np.nan)
    uv[front] = project_pinhole(pts[front], r_wc, c_prior, k)
    r_pred = np.array([lm.diameter_km * 500.0 for lm in cand]) * k[0, 0] / np.where(front, depth, np.nan)
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < width)
    c_true = np.array(row["camera_enu"]["position_m"], dtype=np.float64)
    light = light_direction(rot, to_sun)
    return FrameView(row, (lat0, lon0), r_wc, k, c_true, c_prior, width, fov, gsd, light, cand, pts, uv, r_pred, inside)


def frame_detections(view: FrameView, image, run: FrameRun, refiner, detections=None):
    """(detections, the appearance search's predicted windows or None, why there is none or "", the detector
    settings used): ``detections`` as given, else the appearance search's, else the detector's (on the map's
    radii with ``run.scales_from_map``)."""
    dparams = run.dparams
    if detections is not None:
        return list(detections), None, "", dparams
    if run.appearance is not None:
        sun = view.row["pose"]["to_sun_mc"]
        args = (refiner, view.c_prior, view.r_wc, view.k, view.origin, sun, run.fparams.prior_sigma_km, run.appearance)
        dets, windows = appearance_detections(image, view.cand, view.pts, *args)
        return dets, windows, "", dparams
    if run.scales_from_map:
        dparams = map_scales(dparams, run.fparams, view.gsd, view.r_pred[view.inside])
    try:
        dets, _ = detect(image, dparams, light_dir=view.light, what=f"frame {view.row['rel_path']}")
    except FrameError as exc:  # a frame all in shadow: nothing to detect, an answer of "no fix"
        return [], None, str(exc), dparams
    return dets, None, "", dparams


def detection_scores(view: FrameView, dets, landmarks, fparams: FixParams) -> tuple[dict, dict, int]:
    """(the row's detection fields scored against the frame's labels, landmark id -> index in the row's
    numbering (the map's, then the candidates'), labels in sight)."""
    row = view.row
    by_id = {lm.id: k for k, lm in enumerate(landmarks)}
    by_id.update({lm.id: len(landmarks) + k for k, lm in enumerate(view.cand) if lm.id not in by_id})
    labels = [lb for lb in row["landmarks"] if usable(landmarks[by_id[lb["id"]]], view.gsd, fparams)]
    matched = match_pixels(dets, labels)
    labels_seen = [lb for lb in labels if not hidden(lb)]
    out = {
        "id": f"{row['trajectory']}/{row['index']}",
        "index": row["index"],
        "altitude_km": row["pose"]["altitude_m"] / 1000.0,
        "ground_sample_m": view.gsd,
        "n_detections": len(dets),
        "landmarks_in_view": len(row["landmarks"]),
        "truth": [by_id[lb["id"]] for lb in labels_seen],
        "truth_d_km": [lb["diameter_km"] for lb in labels_seen],
        "det_r_km": [d.r * view.gsd / 1000.0 for d in dets],
        "matched": {k: by_id[labels[j]["id"]] for k, j in matched.items()},
        "matched_any": sorted(matched),
        "detections_px": [[d.u, d.v, d.r, d.score] for d in dets],  # for navigate; not in the JSON
        "n_headline_landmarks": int(sum(lb["diameter_km"] >= HEADLINE_MIN_D_KM for lb in labels_seen)),
    }
    return out, by_id, len(labels_seen)


def putative_pairs(view: FrameView, dets, fparams: FixParams) -> tuple[list[int], list[int]]:
    """(detection, candidate) index pairs the prior allows: the candidate predicted inside the frame within
    the prior's uncertainty (+ r/4 px) of the detection, radii within ``radius_ratio``."""
    pairs_det, pairs_lm = [], []
    if not len(view.pts) or not dets:
        return pairs_det, pairs_lm
    gate_base = fparams.prior_sigma_km * 1000.0 / view.gsd
    for i, d in enumerate(dets):
        dist = np.hypot(view.uv[:, 0] - d.u, view.uv[:, 1] - d.v)
        ratio = d.r / view.r_pred
        ok = (
            view.inside
            & (dist <= gate_base + d.r / 4.0)
            & (ratio <= fparams.radius_ratio)
            & (ratio >= 1 / fparams.radius_ratio)
        )
        for j in np.nonzero(ok)[0]:
            pairs_det.append(i)
            pairs_lm.append(int(j))
    return pairs_det, pairs_lm


@dataclasses.dataclass
class FrameFix:
    """A frame's fix as it is solved: whether it holds (``ok``, else ``reason``), the pose (``r_fix``,
    ``c_fix``), the pairs (``p3`` points, ``p2`` pixels, indices ``pairs_det``/``pairs_lm``), the pairs kept
    (``keep``: one per detection and landmark), their pixels after the ellipse-centre correction
    (``corrected``) and the RMS."""

    ok: bool
    reason: str
    r_fix: np.ndarray
    c_fix: np.ndarray
    p3: np.ndarray
    p2: np.ndarray
    pairs_det: list
    pairs_lm: list
    keep: list = dataclasses.field(default_factory=list)
    corrected: np.ndarray | None = None
    rms: float = math.nan


def solve_frame_fix(view: FrameView, dets, pairs_det, pairs_lm, run: FrameRun) -> FrameFix:
    """RANSAC on the putative pairs (the camera centre with the believed attitude, or the 6-DOF pose), one
    pair per detection and landmark, at least ``min_inliers`` of them, the ellipse-centre correction
    (known attitude) and the RMS check."""
    fparams, k, r_wc = run.fparams, view.k, view.r_wc
    p3 = view.pts[pairs_lm]
    p2 = np.array([[dets[i].u, dets[i].v] for i in pairs_det])
    pair_ids = np.column_stack([pairs_det, pairs_lm])
    if run.method == "pnp":
        args = (p3, p2, k, r_wc, view.c_prior, fparams, run.inlier_px)
        sigma = math.radians(run.pnp_attitude_sigma_deg)
        ok, reason, r_fix, c_fix, inl = ransac_pnp(*args, pairs=pair_ids, attitude_sigma_rad=sigma)
    else:
        r_fix = r_wc
        ok, reason, c_fix, inl = ransac_position(p3, p2, k, r_wc, fparams, run.inlier_px, pairs=pair_ids)
    fix = FrameFix(ok, reason, r_fix, c_fix, p3, p2, pairs_det, pairs_lm)
    if not ok:
        return fix
    # One pair per detection and per landmark: the smallest reprojection error wins.
    err = np.hypot(*(project_pinhole(p3, r_fix, c_fix, k) - p2).T)
    used_d, used_l = set(), set()
    for q in sorted(np.nonzero(inl)[0], key=lambda q: err[q]):
        if pairs_det[q] not in used_d and pairs_lm[q] not in used_l:
            used_d.add(pairs_det[q])
            used_l.add(pairs_lm[q])
            fix.keep.append(q)
    keep = fix.keep
    if len(keep) < fparams.min_inliers:
        fix.ok, fix.reason = False, f"only {len(keep)} distinct landmarks agree on one pose"
        return fix
    if run.method == "position":  # the ellipse-centre correction (refine.ellipse_centre_fix)
        radii = [view.cand[pairs_lm[q]].diameter_km * 500.0 for q in keep]
        fix.c_fix, fix.corrected = ellipse_centre_fix(p3[keep], p2[keep], radii, c_fix, r_wc, k, view.fov, view.width)
        err = np.hypot(*(project_pinhole(p3[keep], r_fix, fix.c_fix, k) - fix.corrected).T)
    else:
        err, fix.corrected = err[keep], p2[keep]
    fix.rms = float(np.sqrt(np.mean(err**2)))
    if fix.rms > fparams.max_rms_px:  # the real-window rule: a loose fit is no fix
        fix.ok, fix.reason = False, f"inlier RMS {fix.rms:.1f} px > {fparams.max_rms_px:g} px"
    return fix


def refine_frame_fix(view: FrameView, image, fix: FrameFix, out: dict, ids, refiner, windows, run: FrameRun):
    """The fix refined by appearance (:meth:`.refine.Refiner.refine`; the 6-DOF pose with ``run.refine_pnp``)
    and verified; the unrefined fix's error and identifications recorded in ``out["unrefined"]``."""
    d = fix.c_fix - view.c_true
    out["unrefined"] = dict(fix=True, error_km=np.linalg.norm(d) / 1e3, error_horizontal_km=np.hypot(*d[:2]) / 1e3)
    good = sum(out["matched"].get(fix.pairs_det[q]) == ids[fix.pairs_lm[q]] for q in fix.keep)
    out["unrefined"].update(identified=len(fix.keep), identified_correct=int(good))
    lms, sun = [view.cand[fix.pairs_lm[q]] for q in fix.keep], view.row["pose"]["to_sun_mc"]
    args = (image, lms, fix.corrected, fix.p3[fix.keep], fix.c_fix, view.r_wc, view.k, view.origin, sun)
    pnp = run.method == "pnp"
    prior = (view.r_wc, math.radians(run.attitude_sigma_deg)) if pnp and run.attitude_sigma_deg > 0 else None
    fix.c_fix, out["refinement"] = refiner.refine(*args, predicted=windows, pose=pnp, attitude_prior=prior)
    if pnp:  # the attitude is refined with the centre
        fix.r_fix = np.asarray(out["refinement"]["rotation"], dtype=np.float64)
    fix.ok, fix.reason = refiner.verified(out["refinement"])


def fix_fields(view: FrameView, fix: FrameFix, out: dict, ids, method: str) -> None:
    """A fix's fields of the row: its position, its own uncertainty, its errors against the truth and its
    identifications."""
    keep, c_fix, r_fix = fix.keep, fix.c_fix, fix.r_fix
    out["position_enu_m"] = [float(v) for v in c_fix]  # the fix (frame ENU): a sequence's next prior
    lat, lon, height = geometry.mc_to_latlon(geometry.enu_to_mc(c_fix, *view.origin))
    out["fix_position"] = {"lat": float(lat), "lon": float(lon), "altitude_m": float(height)}  # sphere
    # Its own uncertainty: how well its landmarks agree (fix.position_sigma_... / fix.pose_sigma_...).
    final = (out.get("refinement") or {}).get("observed_px", fix.corrected)
    if method == "position":
        out["sigma_horizontal_km"] = position_sigma_horizontal_m(fix.p3[keep], final, view.k, view.r_wc, c_fix) / 1e3
    else:  # the 6-DOF fix's attitude (world -> camera, frame ENU) and how far it is from the truth
        out["sigma_horizontal_km"] = pose_sigma_horizontal_m(fix.p3[keep], final, view.k, r_fix, c_fix) / 1000.0
        out["rotation_fix"] = np.asarray(r_fix).tolist()
        out["attitude_error_deg"] = attitude_difference_deg(r_fix, true_camera(view.row)[0])
    out["error_km"] = float(np.linalg.norm(c_fix - view.c_true)) / 1000.0
    # The horizontal part: a few close landmarks fix the altitude less well than the position.
    out["error_horizontal_km"] = float(np.hypot(*(c_fix - view.c_true)[:2])) / 1000.0
    pairs = [[int(fix.pairs_det[q]), int(ids[fix.pairs_lm[q]])] for q in keep]
    out.update(identified=len(keep), identified_pairs=pairs)
    out["identified_correct"] = int(sum(out["matched"].get(fix.pairs_det[q]) == ids[fix.pairs_lm[q]] for q in keep))
    out["rms_px"] = fix.rms


def evaluate_frame(
    row: dict,
    image: np.ndarray,
    landmarks,
    run: FrameRun = FrameRun(),
    refiner=None,
    detections: list | None = None,
    prior_enu: np.ndarray | None = None,
    candidates: list | None = None,
):
    """Detection, identification and fix of one rendered frame with the settings ``run``, scored against its
    labels; a row in :func:`.evaluate.summarise`'s format plus the frame's own fields. ``refiner``
    (:class:`.refine.Refiner`): a known-attitude fix (a 6-DOF one too with ``run.refine_pnp``) is refined
    by appearance, and refused when its landmarks do not register; the appearance search predicts from its
    DEM. ``detections`` replaces the detector's output (the perfect-detection check,
    :func:`perfect_detections`); ``prior_enu``: the prior itself (frame ENU: a sequence's propagated fix,
    :mod:`.sequence`) instead of the truth moved by ``run.prior_offset_km``; ``candidates``: the landmarks
    searched for instead of the usable map landmarks (terrain patches, :mod:`.patches`; ``landmarks`` still
    names the labels). A frame with fewer than ``min_inliers`` labelled landmarks >= ``min_landmark_km`` in
    sight is flagged (``enough_landmarks`` False; a "no fix" there gets the reason
    :data:`NOT_ENOUGH_LANDMARKS`)."""
    fparams = run.fparams
    view = frame_view(row, landmarks, run, prior_enu, candidates)
    dets, windows, empty, dparams = frame_detections(view, image, run, refiner, detections)
    out, by_id, n_seen = detection_scores(view, dets, landmarks, fparams)
    out["detector_radii_px"] = [round(dparams.min_radius_px, 2), round(dparams.max_radius_px, 2)]
    # Fewer map landmarks in the frame than a fix needs: a "no fix" there is no failure of detection
    # (reported apart); the pipeline still runs, so a wrong fix there still counts as one.
    out["enough_landmarks"] = n_seen >= fparams.min_inliers
    ids = [by_id[lm.id] for lm in view.cand]
    pairs_det, pairs_lm = putative_pairs(view, dets, fparams)
    out["putative_pairs"] = len(pairs_det)
    if not pairs_det:
        out.update(fix=False, reason=empty or "no putative landmark pairs")
        if not out["enough_landmarks"]:
            out["reason"] = f"{NOT_ENOUGH_LANDMARKS}: {n_seen} >= {fparams.min_landmark_km:g} km (no pairs)"
        return out
    fix = solve_frame_fix(view, dets, pairs_det, pairs_lm, run)
    if fix.ok and refiner is not None and (run.method == "position" or run.refine_pnp and run.method == "pnp"):
        refine_frame_fix(view, image, fix, out, ids, refiner, windows, run)
    out.update(fix=bool(fix.ok), reason=fix.reason)
    if not fix.ok and not out["enough_landmarks"]:
        out["reason"] = f"{NOT_ENOUGH_LANDMARKS}: {n_seen} >= {fparams.min_landmark_km:g} km ({fix.reason})"
    if fix.ok:
        fix_fields(view, fix, out, ids, run.method)
    return out


# What a frame's row takes from its terrain patches' fix (the rest, detection metrics included, is the craters').
PATCH_FIX_KEYS = ("fix", "reason", "error_km", "error_horizontal_km", "position_enu_m", "fix_position",
                  "sigma_horizontal_km", "rms_px", "refinement", "unrefined", "rotation_fix",
                  "attitude_error_deg")  # fmt: skip


def with_patch_fallback(
    r: dict, row: dict, image, landmarks, refiner, patches: PatchParams, run: FrameRun = FrameRun(), prior_enu=None
):
    """``r`` (a frame's :func:`evaluate_frame` row with its craters) or, when it has no fix, the fix of the
    frame's terrain patches (:mod:`.patches`) searched for by appearance under the same prior, with the same
    identification, fix, refinement and checks (``run``: :func:`evaluate_frame`'s settings). The craters'
    detection metrics stay; ``fix_source`` says which fixed the frame, ``patches`` what the patches gave.
    A patch counts as identified correctly when its detection lies within ``inlier_px`` of where the true
    camera sees the patch's point."""
    if r["fix"]:
        return {**r, "fix_source": "craters"}
    rot = believed_rotation(row, run.seed, run.attitude_error_deg)
    width, fov = int(row["pose"]["width_px"]), float(row["pose"]["fov_deg"])
    r_wc, k = cv_camera(rot, width, fov)
    if prior_enu is None:
        prior_enu = prior_centre(row, run.seed, run.prior_offset_km)
    origin = (row["frame_origin"]["lat"], row["frame_origin"]["lon"])
    found = patch_landmarks(refiner.dem, prior_enu, r_wc, k, width, origin, pole_of(origin[0]), patches)
    info = {"searched": len(found)}
    if not found:
        return {**r, "fix_source": None, "patches": {**info, "reason": "no patch on the DEM"}}
    rp = evaluate_frame(row, image, landmarks, run, refiner=refiner, prior_enu=prior_enu, candidates=found)
    info.update(found=rp["n_detections"], reason=rp["reason"])
    if not rp["fix"]:
        return {**r, "fix_source": None, "patches": info}
    # Identification truth of a patch: where the true camera sees its point (the ellipse centre, as detected);
    # and where each was found (centre, window half-width px): what `navigate` draws.
    r_true, _ = true_camera(row)
    c_true = np.array(row["camera_enu"]["position_m"], dtype=np.float64)
    correct, drawn = 0, []
    for det, ident in rp["identified_pairs"]:
        lm = found[ident - len(landmarks)]
        point = geometry.mc_to_enu(lm.position_mc()[None], *origin)
        (ell,) = rim_ellipses(point, [lm.diameter_km * 500.0], c_true, r_true, fov, width)
        u, v = rp["detections_px"][det][:2]
        correct += int(math.hypot(u - ell.cu, v - ell.cv) <= run.inlier_px)
        half_px = lm.diameter_km * RefineParams().window_diameters * 1000.0 / float(row["ground_sample_m"])
        drawn.append([round(u, 2), round(v, 2), round(half_px, 1)])
    info.update(identified=rp["identified"], identified_correct=correct, identified_px=drawn)
    out = {**r, **{key: rp[key] for key in PATCH_FIX_KEYS if key in rp}, "fix_source": "patches", "patches": info}
    out.update(identified=rp["identified"], identified_correct=correct, identified_pairs=[])
    if "unrefined" in out:  # the same identifications before the refinement
        out["unrefined"] = {**out["unrefined"], "identified_correct": correct}
    return out


def perfect_detections(row: dict) -> list[Detection]:
    """Every label's own rim ellipse as a detection (centre, semi-major axis): the perfect-detection check's
    input (labels, projection, identification and fix tested without the detector)."""
    return [Detection(lb["ellipse"]["cu"], lb["ellipse"]["cv"], lb["ellipse"]["a"], 1.0) for lb in row["landmarks"]]


@dataclasses.dataclass(frozen=True)
class DirOptions:
    """What :func:`evaluate_dir` does besides each frame's settings: ``sensor`` a camera model applied to each
    frame first (``--sensor``); ``terrain_workers`` processes preparing each frame's new landmark windows
    (:class:`.refine.Refiner`; the same results); ``patches`` (with the appearance search): a frame its craters
    do not fix is navigated with its terrain patches (:func:`with_patch_fallback`); ``sequence``: each frame's
    prior is the last fix of its trajectory carried forward (:mod:`.sequence`; frames in index order; the
    first, and any the drift leaves no tighter than ``fix.prior_sigma_km``, get the standard prior);
    ``dem_error``: the lander's DEM carries this height error (:mod:`.dem_error`; the frames stay as
    rendered, the perfect-detection check is unaffected)."""

    sensor: Any = None
    terrain_workers: int = 1
    patches: PatchParams | None = None
    sequence: SequenceParams | None = None
    dem_error: DemErrorParams | None = None


def pole_refiner(pole: str, run: FrameRun, options: DirOptions):
    """The refiner of a pole's frames (None unless the run refines or searches by appearance: only these
    predict from the lander's DEM); the DEM perturbed by ``options.dem_error``, seeded like the prior
    offsets."""
    if not (run.refine or run.appearance):
        return None
    dem = lander_dem(pole)
    if options.dem_error is not None:
        dem = PerturbedDem(dem, options.dem_error, pole, run.seed)
    return Refiner(dem, workers=options.terrain_workers)


def evaluate_dir_frame(row: dict, image, landmarks, refiner, run: FrameRun, options: DirOptions, last: dict) -> dict:
    """One frame of :func:`evaluate_dir`: its row (the patch fallback, the sequence's prior and the timing
    included) with the perfect-detection row under ``"perfect"``; ``last`` (trajectory -> its last fix) is
    updated."""
    prior = None
    if options.sequence is not None and row["trajectory"] in last:
        prior = propagated_prior(row, last[row["trajectory"]], options.sequence, run.seed, run.fparams.prior_sigma_km)
    this_run = run
    if prior is not None:  # the propagated prior's own uncertainty gates the identification
        this_run = dataclasses.replace(run, fparams=dataclasses.replace(run.fparams, prior_sigma_km=prior[1]))
    t0 = time.perf_counter()
    prior_enu = None if prior is None else prior[0]
    r = evaluate_frame(row, image, landmarks, this_run, refiner=refiner, prior_enu=prior_enu)
    if options.patches is not None and run.appearance is not None:
        r = with_patch_fallback(r, row, image, landmarks, refiner, options.patches, this_run, prior_enu)
    r["prior_sigma_km"] = this_run.fparams.prior_sigma_km
    if options.sequence is not None and r["fix"]:
        last[row["trajectory"]] = last_fix(row, r)
    r["seconds"] = round(time.perf_counter() - t0, 3)  # detection, identification, fix and refinement
    # The perfect-detection check: the true attitude and the default prior, no refinement.
    perfect = FrameRun(run.dparams, run.fparams, seed=run.seed, method=run.method, inlier_px=run.inlier_px)
    r["perfect"] = evaluate_frame(row, image, landmarks, perfect, detections=perfect_detections(row))
    return r


def dir_summary(out: list[dict], refine: bool) -> dict:
    """The summaries of a directory's rows: all, headline and enough-landmarks frames, with the detector and
    with perfect detections, the time per frame, and (``refine``) the same fixes before their refinement."""
    head = [r for r in out if r["n_headline_landmarks"] >= HEADLINE_MIN_LANDMARKS]
    enough = [r for r in out if r["enough_landmarks"]]
    summary = {
        "all": rendered_summary(out),
        "headline": rendered_summary(head),
        "enough_landmarks": rendered_summary(enough),
        "not_enough_landmarks": len(out) - len(enough),
        "perfect": {
            "all": rendered_summary([r["perfect"] for r in out]),
            "headline": rendered_summary([r["perfect"] for r in head]),
            "enough_landmarks": rendered_summary([r["perfect"] for r in enough]),
        },
        "seconds_per_frame": sorted(r["seconds"] for r in out),
    }
    if refine:  # the same fixes before their refinement: the plain fix's accuracy, in the same run
        plain = {r["id"]: {**r, **r.get("unrefined", {})} for r in out}  # a fix the appearance check refused too
        groups = (("all", out), ("headline", head), ("enough_landmarks", enough))
        summary["unrefined"] = {name: rendered_summary([plain[r["id"]] for r in rows]) for name, rows in groups}
        summary["refine_seconds"] = [r["refinement"]["seconds"] for r in out if "refinement" in r]
    return summary


def evaluate_dir(
    frames_dir: Path, run: FrameRun = FrameRun(), options: DirOptions = DirOptions(), progress: bool = False
):
    """(summaries, per-frame rows) of a ``nav-frames`` output navigated with the settings ``run``
    (:func:`evaluate_frame`; ``run.refine``: the fixes are refined by appearance with the pole's
    :func:`.refine.lander_dem`, summarised without it under ``"unrefined"``) and the ``options``
    (:class:`DirOptions`): the summaries over all frames, the headline frames and the frames with at least
    ``min_inliers`` landmarks in view (``"enough_landmarks"``), with the detector and with perfect detections
    (``"perfect"``: the true attitude and the default prior); each row is the detector's, with the
    perfect-detection row of the same frame under ``"perfect"``. ``progress``: the frames done, with rate and
    ETA, on stderr."""
    maps: dict[str, list] = {}
    last: dict[str, dict] = {}  # trajectory -> its last fix (sequence)
    refiners: dict[str, Refiner | None] = {}
    out = []
    rows = labelled_rows(frames_dir)
    if options.sequence is not None:  # each trajectory's frames in flight order
        rows = sorted(rows, key=lambda r: (r["trajectory"], r["index"]))
    bar = Progress(len(rows), "nav-frames-eval", "frame", "auto" if progress else "off")
    for row in rows:
        pole = pole_of(row["frame_origin"]["lat"])
        if pole not in maps:
            maps[pole] = load_default_map(pole)[0]
            refiners[pole] = pole_refiner(pole, run, options)
        image = exr.read_channel(Path(frames_dir) / row["rel_path"], "IF")
        if options.sensor is not None:  # a camera on the I/F frame (train.preprocess.SensorModel), seeded per frame
            image = options.sensor.apply(image, np.random.default_rng([run.seed, zlib.crc32(row["rel_path"].encode())]))
        out.append(evaluate_dir_frame(row, image, maps[pole], refiners[pole], run, options, last))
        bar.update()
    bar.close()
    for refiner in refiners.values():
        if refiner is not None:
            refiner.close()
    return dir_summary(out, run.refine), out
