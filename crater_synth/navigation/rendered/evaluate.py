"""Navigation metrics on rendered frames with exact truth (``crater-synth nav-frames-eval DIR``).

The same pipeline and metrics as ``crater-synth nav-eval`` on real mosaic windows
(:mod:`.evaluate`), for the perspective frames of ``crater-synth nav-frames``:

- **Detection**: :func:`.detect.detect` on the I/F channel, with the settings of a preset
  (``nav/preset``, configs/nav/preset/; "synthetic", the classical detector's settings chosen on rendered frames;
  "learned"; "real-window": the real windows' settings unchanged), or no detector: the default
  "appearance" preset searches for the map's landmarks by their predicted appearance (:mod:`.appearance`).
  The light direction in the image is given (the lander knows its attitude and the ephemeris): the Sun's
  travel direction, projected on the image plane. The "synthetic" preset searches only the radii the map
  can use in the frame (:func:`map_scales`: from the ground sample, as a lander knowing its altitude would).
- **Truth**: the frame's labels (every landmark whose rim centre projects inside the frame, with its
  projected rim ellipse; :mod:`.render_frames`), less those whose rim is mostly hidden behind nearer
  relief (:data:`.frame_labels.HIDDEN_RIM_MAX`): they are not counted as misses, nor a detection on
  them as false. A detection matches a label when its centre is within 0.25 D of the ellipse centre
  and its radius within 25 % of the ellipse's semi-major axis.
- **Prior**: the true camera moved ``PRIOR_OFFSET_KM`` horizontally in a seeded random direction;
  the attitude is the true one (the same assumption as nav-eval's exact prior heading and scale).
- **Identification**: map landmarks >= ``min_landmark_km`` (those a finer DEM layer added: from
  ``LAYER_LANDMARK_MIN_PX`` px) projected with the prior pose; putative pairs within the prior's
  uncertainty (``prior_sigma_km`` / ground sample + r/4 px) and radius ratio within ``radius_ratio``
  (:class:`.fix.FixParams`, the values chosen on real validation windows).
- **Fix** (``method``): ``position`` (default): the camera centre with the prior's (true) attitude,
  :func:`.fix.ransac_position` (least squares on the rays through the landmarks' 3-D rim-centre
  points, minimal sets of 2), corrected for the perspective offset of the rim ellipses' centres
  (:func:`.refine.ellipse_centre_fix`); ``pnp``: the full pose, :func:`.fix.ransac_pnp`. One pair per
  detection and landmark; "no fix" when fewer than ``min_inliers`` distinct landmarks agree, when a
  disjoint rival set nearly as large agrees (the ambiguity test; known attitude) or when their RMS
  exceeds ``max_rms_px``. Presets with ``refine`` then register each fix landmark's predicted
  appearance on the frame and solve again (:mod:`.refine`; a 6-DOF fix with ``refine_pnp``, attitude
  too). A frame with fewer than ``min_inliers`` landmarks in view is flagged and summarised apart. The
  error is the 3-D distance between the fixed and the true camera centre (horizontal part too); a fix is
  false beyond ``FALSE_FIX_KM``.
- **Options**: terrain patches where the craters give no fix (:func:`with_patch_fallback`), each frame's
  prior from its trajectory's last fix (:mod:`.sequence`).

Metrics are :func:`.evaluate.summarise`'s (one definition for real and rendered frames). The command
is :mod:`.frames_eval_cli`.

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

import numpy as np

from crater_core import exr, geometry
from crater_core.settings_nav import AppearanceSettings, DetectorSettings, FramesSettings
from crater_synth.navigation.detectors.classical import ClassicalSettings, Detection, detect
from crater_synth.navigation.fix.appearance import appearance_detections
from crater_synth.navigation.fix.patches import PatchParams, patch_landmarks
from crater_synth.navigation.fix.refine import RefineParams, Refiner, ellipse_centre_fix, lander_dem, rim_ellipses
from crater_synth.navigation.fix.sequence import SequenceParams, last_fix, propagated_prior
from crater_synth.navigation.fix.solve import (
    FixParams,
    attitude_difference_deg,
    pose_sigma_horizontal_m,
    position_sigma_horizontal_m,
    project_pinhole,
    ransac_pnp,
    ransac_position,
    rodrigues,
)
from crater_synth.navigation.georef import FrameError, pole_of
from crater_synth.navigation.map.dem_error import DemErrorParams, PerturbedDem
from crater_synth.navigation.map.landmarks import positions_mc
from crater_synth.navigation.protocol import (
    HEADLINE_MIN_D_KM,
    HEADLINE_MIN_LANDMARKS,
    MATCH_CENTRE_D,
    MATCH_DIAMETER,
    PRIOR_OFFSET_KM,
    rendered_summary,
)
from crater_synth.navigation.rendered.labels import hidden
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


def light_direction(rotation: np.ndarray, to_sun: np.ndarray) -> float:
    """Image azimuth (radians, atan2(dv, du), v down) of the light's travel direction (away from the Sun)."""
    travel = -np.asarray(to_sun, dtype=np.float64)
    return math.atan2(-(travel @ rotation[:, 1]), travel @ rotation[:, 0])


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


def evaluate_frame(
    row: dict,
    image: np.ndarray,
    landmarks,
    dparams: DetectorSettings,
    fparams: FixParams,
    seed: int = 0,
    method: str = "position",
    detections: list | None = None,
    scales_from_map: bool = False,
    inlier_px: float = PNP_INLIER_PX,
    refiner=None,
    appearance: AppearanceSettings | None = None,
    attitude_error_deg: float = 0.0,
    prior_offset_km: float = PRIOR_OFFSET_KM,
    prior_enu: np.ndarray | None = None,
    candidates: list | None = None,
    refine_pnp: bool = False,
    attitude_sigma_deg: float = 0.0,
):
    """Detection, identification and fix of one rendered frame, scored against its labels; a row in
    :func:`.evaluate.summarise`'s format plus the frame's own fields. ``detections`` replaces the
    detector's output (the perfect-detection check, :func:`perfect_detections`). ``scales_from_map``:
    the detector searches only the radii of the map landmarks the prior predicts in the frame
    (:func:`map_scales`); ``inlier_px``: the fix's reprojection inlier tolerance; ``refiner``
    (:class:`.refine.Refiner`): a known-attitude fix (a 6-DOF one too with ``refine_pnp``, weighted towards
    the believed attitude by its 1-sigma ``attitude_sigma_deg`` when > 0) is refined by appearance, and
    refused when its landmarks do not register; ``appearance``: no detector, the landmarks
    are searched for by their predicted appearance (:mod:`.appearance`, the refiner's DEM);
    ``attitude_error_deg``: the pipeline works with the attitude turned by this angle about a seeded axis
    (the lander's attitude error; the image and the truth are the frame's); ``prior_offset_km``: how far the
    prior is from the true camera (horizontally, seeded direction), or ``prior_enu`` the prior itself (frame
    ENU: a sequence's propagated fix, :mod:`.sequence`); ``candidates``: the landmarks searched for instead
    of the usable map landmarks (terrain patches, :mod:`.patches`; ``landmarks`` still names the labels). A
    frame with fewer than ``min_inliers`` labelled landmarks >= ``min_landmark_km`` in sight is flagged
    (``enough_landmarks`` False; a "no fix" there gets the reason :data:`NOT_ENOUGH_LANDMARKS`)."""
    lat0, lon0 = row["frame_origin"]["lat"], row["frame_origin"]["lon"]
    rot = believed_rotation(row, seed, attitude_error_deg)
    c_true = np.array(row["camera_enu"]["position_m"], dtype=np.float64)
    width = int(row["pose"]["width_px"])
    fov = float(row["pose"]["fov_deg"])
    gsd = float(row["ground_sample_m"])
    to_sun = geometry.direction_from_elevation_azimuth(row["sun_enu"]["elevation_deg"], row["sun_enu"]["azimuth_deg"])
    # The map landmarks the prior predicts in the frame (position and radius, px).
    r_wc, k = cv_camera(rot, width, fov)
    c_prior = prior_centre(row, seed, prior_offset_km) if prior_enu is None else np.asarray(prior_enu, dtype=float)
    cand = [lm for lm in landmarks if usable(lm, gsd, fparams)] if candidates is None else list(candidates)
    pts = geometry.mc_to_enu(positions_mc(cand), lat0, lon0) if cand else np.zeros((0, 3))
    depth = (pts - c_prior) @ r_wc[2]
    front = depth > 0
    uv = np.full((len(pts), 2), np.nan)
    uv[front] = project_pinhole(pts[front], r_wc, c_prior, k)
    r_pred = np.array([lm.diameter_km * 500.0 for lm in cand]) * k[0, 0] / np.where(front, depth, np.nan)
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < width)
    windows, empty = None, ""  # the appearance search's predicted windows (for the refinement); why no detections
    if detections is None and appearance is not None:
        sun = row["pose"]["to_sun_mc"]
        args = (refiner, c_prior, r_wc, k, (lat0, lon0), sun, fparams.prior_sigma_km, appearance)
        dets, windows = appearance_detections(image, cand, pts, *args)
    elif detections is None:
        if scales_from_map:
            dparams = map_scales(dparams, fparams, gsd, r_pred[inside])
        try:
            dets, _ = detect(image, dparams, light_dir=light_direction(rot, to_sun), what=f"frame {row['rel_path']}")
        except FrameError as exc:  # a frame all in shadow: nothing to detect, an answer of "no fix"
            dets, empty = [], str(exc)
    else:
        dets = list(detections)
    by_id = {lm.id: k for k, lm in enumerate(landmarks)}
    by_id.update({lm.id: len(landmarks) + k for k, lm in enumerate(cand) if lm.id not in by_id})
    labels = [lb for lb in row["landmarks"] if usable(landmarks[by_id[lb["id"]]], gsd, fparams)]
    matched = match_pixels(dets, labels)
    labels_seen = [lb for lb in labels if not hidden(lb)]
    out = {
        "id": f"{row['trajectory']}/{row['index']}",
        "index": row["index"],
        "altitude_km": row["pose"]["altitude_m"] / 1000.0,
        "ground_sample_m": gsd,
        "n_detections": len(dets),
        "landmarks_in_view": len(row["landmarks"]),
        "truth": [by_id[lb["id"]] for lb in labels_seen],
        "truth_d_km": [lb["diameter_km"] for lb in labels_seen],
        "det_r_km": [d.r * gsd / 1000.0 for d in dets],
        "matched": {k: by_id[labels[j]["id"]] for k, j in matched.items()},
        "matched_any": sorted(matched),
        "detections_px": [[d.u, d.v, d.r, d.score] for d in dets],  # for navigate; not in the JSON
        "n_headline_landmarks": int(sum(lb["diameter_km"] >= HEADLINE_MIN_D_KM for lb in labels_seen)),
    }
    out["detector_radii_px"] = [round(dparams.min_radius_px, 2), round(dparams.max_radius_px, 2)]
    # Fewer map landmarks in the frame than a fix needs: a "no fix" there is no failure of detection
    # (reported apart); the pipeline still runs, so a wrong fix there still counts as one.
    out["enough_landmarks"] = len(labels_seen) >= fparams.min_inliers
    # Identification with the prior pose.
    ids = [by_id[lm.id] for lm in cand]
    pairs_det, pairs_lm = [], []
    if len(pts) and dets:
        gate_base = fparams.prior_sigma_km * 1000.0 / gsd
        for i, d in enumerate(dets):
            dist = np.hypot(uv[:, 0] - d.u, uv[:, 1] - d.v)
            ratio = d.r / r_pred
            ok = (
                inside
                & (dist <= gate_base + d.r / 4.0)
                & (ratio <= fparams.radius_ratio)
                & (ratio >= 1 / fparams.radius_ratio)
            )
            for j in np.nonzero(ok)[0]:
                pairs_det.append(i)
                pairs_lm.append(int(j))
    out["putative_pairs"] = len(pairs_det)
    if not pairs_det:
        out.update(fix=False, reason=empty or "no putative landmark pairs")
        if not out["enough_landmarks"]:
            out["reason"] = f"{NOT_ENOUGH_LANDMARKS}: {len(labels_seen)} >= {fparams.min_landmark_km:g} km (no pairs)"
        return out
    p3 = pts[pairs_lm]
    p2 = np.array([[dets[i].u, dets[i].v] for i in pairs_det])
    pair_ids = np.column_stack([pairs_det, pairs_lm])
    if method == "pnp":
        ok, reason, r_fix, c_fix, inl = ransac_pnp(p3, p2, k, r_wc, c_prior, fparams, inlier_px, pairs=pair_ids)
    else:
        r_fix = r_wc
        ok, reason, c_fix, inl = ransac_position(p3, p2, k, r_wc, fparams, inlier_px, pairs=pair_ids)
    if ok:
        # One pair per detection and per landmark: the smallest reprojection error wins.
        err = np.hypot(*(project_pinhole(p3, r_fix, c_fix, k) - p2).T)
        used_d, used_l, keep = set(), set(), []
        for q in sorted(np.nonzero(inl)[0], key=lambda q: err[q]):
            if pairs_det[q] not in used_d and pairs_lm[q] not in used_l:
                used_d.add(pairs_det[q])
                used_l.add(pairs_lm[q])
                keep.append(q)
        if len(keep) < fparams.min_inliers:
            ok, reason = False, f"only {len(keep)} distinct landmarks agree on one pose"
        elif method == "position":  # the ellipse-centre correction (refine.ellipse_centre_fix)
            radii = [cand[pairs_lm[q]].diameter_km * 500.0 for q in keep]
            c_fix, corrected = ellipse_centre_fix(p3[keep], p2[keep], radii, c_fix, r_wc, k, fov, width)
            err = np.hypot(*(project_pinhole(p3[keep], r_fix, c_fix, k) - corrected).T)
        else:
            err, corrected = err[keep], p2[keep]
        rms = float(np.sqrt(np.mean(err**2))) if ok else math.nan
        if ok and rms > fparams.max_rms_px:  # the real-window rule: a loose fit is no fix
            ok, reason = False, f"inlier RMS {rms:.1f} px > {fparams.max_rms_px:g} px"
    if ok and refiner is not None and (method == "position" or refine_pnp and method == "pnp"):
        d = c_fix - c_true
        out["unrefined"] = dict(fix=True, error_km=np.linalg.norm(d) / 1e3, error_horizontal_km=np.hypot(*d[:2]) / 1e3)
        good = sum(out["matched"].get(pairs_det[q]) == ids[pairs_lm[q]] for q in keep)
        out["unrefined"].update(identified=len(keep), identified_correct=int(good))
        lms, sun = [cand[pairs_lm[q]] for q in keep], row["pose"]["to_sun_mc"]
        args = (image, lms, corrected, p3[keep], c_fix, r_wc, k, (lat0, lon0), sun)
        prior = (r_wc, math.radians(attitude_sigma_deg)) if method == "pnp" and attitude_sigma_deg > 0 else None
        c_fix, out["refinement"] = refiner.refine(*args, predicted=windows, pose=method == "pnp", attitude_prior=prior)
        if method == "pnp":  # the attitude is refined with the centre
            r_fix = np.asarray(out["refinement"]["rotation"], dtype=np.float64)
        ok, reason = refiner.verified(out["refinement"])
    out.update(fix=bool(ok), reason=reason)
    if not ok and not out["enough_landmarks"]:
        out["reason"] = f"{NOT_ENOUGH_LANDMARKS}: {len(labels_seen)} >= {fparams.min_landmark_km:g} km ({reason})"
    if ok:
        out["position_enu_m"] = [float(v) for v in c_fix]  # the fix (frame ENU): a sequence's next prior
        lat, lon, height = geometry.mc_to_latlon(geometry.enu_to_mc(c_fix, lat0, lon0))
        out["fix_position"] = {"lat": float(lat), "lon": float(lon), "altitude_m": float(height)}  # sphere
        # Its own uncertainty: how well its landmarks agree (fix.position_sigma_... / fix.pose_sigma_...).
        final = (out.get("refinement") or {}).get("observed_px", corrected)
        if method == "position":
            out["sigma_horizontal_km"] = position_sigma_horizontal_m(p3[keep], final, k, r_wc, c_fix) / 1000.0
        else:  # the 6-DOF fix's attitude (world -> camera, frame ENU) and how far it is from the truth
            out["sigma_horizontal_km"] = pose_sigma_horizontal_m(p3[keep], final, k, r_fix, c_fix) / 1000.0
            out["rotation_fix"] = np.asarray(r_fix).tolist()
            out["attitude_error_deg"] = attitude_difference_deg(r_fix, true_camera(row)[0])
        out["error_km"] = float(np.linalg.norm(c_fix - c_true)) / 1000.0
        # The horizontal part: a few close landmarks fix the altitude less well than the position.
        out["error_horizontal_km"] = float(np.hypot(*(c_fix - c_true)[:2])) / 1000.0
        out.update(identified=len(keep), identified_pairs=[[int(pairs_det[q]), int(ids[pairs_lm[q]])] for q in keep])
        out["identified_correct"] = int(sum(out["matched"].get(pairs_det[q]) == ids[pairs_lm[q]] for q in keep))
        out["rms_px"] = rms
    return out


# What a frame's row takes from its terrain patches' fix (the rest, detection metrics included, is the craters').
PATCH_FIX_KEYS = ("fix", "reason", "error_km", "error_horizontal_km", "position_enu_m", "fix_position",
                  "sigma_horizontal_km", "rms_px", "refinement", "unrefined", "rotation_fix",
                  "attitude_error_deg")  # fmt: skip


def with_patch_fallback(r: dict, row: dict, image, landmarks, refiner, patches: PatchParams, prior_enu=None, **kw):
    """``r`` (a frame's :func:`evaluate_frame` row with its craters) or, when it has no fix, the fix of the
    frame's terrain patches (:mod:`.patches`) searched for by appearance under the same prior, with the same
    identification, fix, refinement and checks (``kw``: :func:`evaluate_frame`'s settings). The craters'
    detection metrics stay; ``fix_source`` says which fixed the frame, ``patches`` what the patches gave.
    A patch counts as identified correctly when its detection lies within ``inlier_px`` of where the true
    camera sees the patch's point."""
    if r["fix"]:
        return {**r, "fix_source": "craters"}
    seed = kw.get("seed", 0)
    rot = believed_rotation(row, seed, kw.get("attitude_error_deg", 0.0))
    width, fov = int(row["pose"]["width_px"]), float(row["pose"]["fov_deg"])
    r_wc, k = cv_camera(rot, width, fov)
    if prior_enu is None:
        prior_enu = prior_centre(row, seed, kw.get("prior_offset_km", PRIOR_OFFSET_KM))
    origin = (row["frame_origin"]["lat"], row["frame_origin"]["lon"])
    found = patch_landmarks(refiner.dem, prior_enu, r_wc, k, width, origin, pole_of(origin[0]), patches)
    info = {"searched": len(found)}
    if not found:
        return {**r, "fix_source": None, "patches": {**info, "reason": "no patch on the DEM"}}
    rp = evaluate_frame(row, image, landmarks, refiner=refiner, prior_enu=prior_enu, candidates=found, **kw)
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
        correct += int(math.hypot(u - ell.cu, v - ell.cv) <= kw.get("inlier_px", PNP_INLIER_PX))
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


def evaluate_dir(
    frames_dir: Path,
    dparams: DetectorSettings = ClassicalSettings(),
    fparams: FixParams = FixParams(),
    seed: int = 0,
    method: str = "position",
    scales_from_map: bool = False,
    inlier_px: float = PNP_INLIER_PX,
    refine: bool = False,
    appearance: AppearanceSettings | None = None,
    sensor=None,
    attitude_error_deg: float = 0.0,
    prior_offset_km: float = PRIOR_OFFSET_KM,
    terrain_workers: int = 1,
    patches: PatchParams | None = None,
    sequence: SequenceParams | None = None,
    dem_error: DemErrorParams | None = None,
    refine_pnp: bool = False,
    attitude_sigma_deg: float = 0.0,
):
    """(summaries, per-frame rows) of a ``nav-frames`` output: the summaries over all frames, the
    headline frames and the frames with at least ``min_inliers`` landmarks in view (``"enough_landmarks"``),
    with the detector and with perfect detections (``"perfect"``); each row is the detector's, with the
    perfect-detection row of the same frame under ``"perfect"``. ``refine``: the detector's fixes are refined
    by appearance with the pole's :func:`.refine.lander_dem` (summarised without it under ``"unrefined"``);
    ``appearance``: the landmarks are searched for by their predicted appearance instead of detected;
    ``sensor``: a camera model applied to each frame first (``--sensor``); ``attitude_error_deg``: the
    lander's attitude error and ``prior_offset_km`` the prior's distance from the truth (:func:`evaluate_frame`;
    the perfect-detection check keeps the true attitude and the default prior); ``terrain_workers``: processes
    preparing each frame's new landmark windows (:class:`.refine.Refiner`; the same results); ``patches``
    (with ``appearance``): a frame its craters do not fix is navigated with its terrain patches
    (:func:`with_patch_fallback`); ``sequence``: each frame's prior is the last fix of its trajectory carried
    forward (:mod:`.sequence`; frames in index order; the first, and any the drift leaves no tighter than
    ``fix.prior_sigma_km``, get the standard prior); ``dem_error``: the lander's DEM carries this height
    error (:mod:`.dem_error`; the frames stay as rendered, the perfect-detection check is unaffected);
    ``refine_pnp``, ``attitude_sigma_deg``: :func:`evaluate_frame`'s."""
    from crater_synth.navigation.map.landmarks import load_default_map
    from crater_synth.navigation.rendered.labels import labelled_rows

    maps: dict[str, list] = {}
    last: dict[str, dict] = {}  # trajectory -> its last fix (sequence)
    refiners: dict[str, Refiner] = {}
    out = []
    rows = labelled_rows(frames_dir)
    if sequence is not None:  # each trajectory's frames in flight order
        rows = sorted(rows, key=lambda r: (r["trajectory"], r["index"]))
    for row in rows:
        pole = pole_of(row["frame_origin"]["lat"])
        if pole not in maps:
            maps[pole] = load_default_map(pole)[0]
            refiners[pole] = None
            if refine or appearance:  # only these predict from the lander's DEM: open it only for them
                dem = lander_dem(pole)
                if dem_error is not None:  # seeded like the prior offsets
                    dem = PerturbedDem(dem, dem_error, pole, seed)
                refiners[pole] = Refiner(dem, workers=terrain_workers)
        image = exr.read_channel(Path(frames_dir) / row["rel_path"], "IF")
        if sensor is not None:  # a camera on the I/F frame (train.preprocess.SensorModel), seeded per frame
            image = sensor.apply(image, np.random.default_rng([seed, zlib.crc32(row["rel_path"].encode())]))
        kw = dict(seed=seed, method=method, inlier_px=inlier_px)
        prior = None
        if sequence is not None and row["trajectory"] in last:
            prior = propagated_prior(row, last[row["trajectory"]], sequence, seed, fparams.prior_sigma_km)
        fp = fparams if prior is None else dataclasses.replace(fparams, prior_sigma_km=prior[1])
        nav = dict(
            dparams=dparams,
            fparams=fp,
            scales_from_map=scales_from_map,
            appearance=appearance,
            attitude_error_deg=attitude_error_deg,
            prior_offset_km=prior_offset_km,
            refine_pnp=refine_pnp,
            attitude_sigma_deg=attitude_sigma_deg,
            **kw,
        )
        t0 = time.perf_counter()
        prior_enu = None if prior is None else prior[0]
        r = evaluate_frame(row, image, maps[pole], refiner=refiners[pole], prior_enu=prior_enu, **nav)
        if patches is not None and appearance is not None:
            r = with_patch_fallback(r, row, image, maps[pole], refiners[pole], patches, prior_enu, **nav)
        r["prior_sigma_km"] = fp.prior_sigma_km
        if sequence is not None and r["fix"]:
            last[row["trajectory"]] = last_fix(row, r)
        r["seconds"] = round(time.perf_counter() - t0, 3)  # detection, identification, fix and refinement
        r["perfect"] = evaluate_frame(
            row, image, maps[pole], dparams, fparams, detections=perfect_detections(row), **kw
        )
        out.append(r)
    for refiner in refiners.values():
        if refiner is not None:
            refiner.close()
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
    return summary, out
