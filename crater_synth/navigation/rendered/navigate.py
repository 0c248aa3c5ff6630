"""``crater-synth navigate FRAME.exr``: one rendered navigation frame through ``nav-frames-eval``'s pipeline.

A frame of ``crater-synth nav-frames`` (perspective, any attitude) is not a north-up map window, so
``navigate`` hands it here: its row in the ``manifest.jsonl`` beside it gives the camera pose and the Sun;
the detector and fix settings are a ``nav/preset`` (configs/nav/preset/);
the prior is ``nav-frames-eval``'s (the true camera moved 5 km, the true attitude) and the fix the
known-attitude camera centre (:func:`.evaluate.evaluate_frame`; with ``six_dof`` the 6-DOF pose), refined
by appearance where the preset says so (:mod:`..fix.refine`). Its truth is exact, so the error is
the 3-D distance between the fixed and the true camera centre. Writes an annotated PNG (the labelled
rims thin green, the detections red dashed, the identified landmarks yellow with their names) and the
per-detection list (circle, confidence, landmark identified or "unknown", the labelled landmark it
matches) as JSON beside it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from crater_core import exr, geometry, schema
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.patches import PatchParams
from crater_synth.navigation.fix.pose import project_pinhole
from crater_synth.navigation.fix.refine import Refiner, lander_dem
from crater_synth.navigation.georef import FrameError, pole_of
from crater_synth.navigation.map.landmarks import load_default_map
from crater_synth.navigation.output import detection_records, draw_detections, png_of, write_detections
from crater_synth.navigation.rendered.evaluate import evaluate_frame, frame_run, true_camera, with_patch_fallback
from crater_synth.navigation.rendered.labels import labelled_rows


def frame_row_of(image: Path) -> dict:
    """The manifest row of the rendered frame ``image``, its file checked against the row (sha256, header); a frame
    with no manifest beside it, or not in it, or changed since it was written, is one error line."""
    manifest = image.parent / schema.MANIFEST_NAME
    if not image.is_file():
        raise FrameError(f"{image}: no such file")
    if not manifest.is_file():
        raise FrameError(
            f"{image}: no {schema.MANIFEST_NAME} beside it; a rendered frame is navigated with the pose its "
            "manifest row holds (render frames with `crater-synth nav-frames`)"
        )

    rows = [r for r in labelled_rows(image.parent, only=image.name) if r.get("rel_path") == image.name]
    if not rows:
        raise FrameError(f"{image}: not a frame of {manifest}")
    return rows[0]  # its file checked by labelled_rows (verify's check, or a recorded verify pass)


def navigate_rendered_frame(
    image: Path, nav, out: Path, seed: int = 0, patches: bool = False, six_dof: bool = False
) -> dict:
    """Detect, identify and fix one rendered frame with the navigation settings ``nav`` (a ``nav/preset``,
    :func:`..settings.compose_nav`); writes
    the annotated PNG ``out`` and returns the result (one JSON object). ``patches``: a frame its craters do
    not fix is navigated with terrain patches (:func:`.evaluate.with_patch_fallback`; the appearance
    preset only); ``six_dof``: the 6-DOF fix (attitude too, ``nav.frames.solver=pnp``), refined by
    appearance where the preset refines."""
    row = frame_row_of(image)
    try:
        img = exr.read_channel(image, "IF")
    except exr.ExrError as exc:
        raise FrameError(str(exc)) from None
    pole = pole_of(row["frame_origin"]["lat"])
    landmarks = load_default_map(pole)[0]
    preset = nav.preset or nav.choices["detector"]
    run = frame_run(nav, seed=seed, method="pnp" if six_dof else "position", refine_pnp=six_dof)
    refiner = Refiner(lander_dem(pole)) if run.refine or run.appearance else None
    r = evaluate_frame(row, img, landmarks, run, refiner=refiner)
    if patches:
        if run.appearance is None:
            raise FrameError(f"--patches needs the appearance search, not the {preset} preset")
        r = with_patch_fallback(r, row, img, landmarks, refiner, PatchParams(), run)
    result = {
        "image": str(image),
        "preset": preset,
        "detector": nav.detector.method,
        "position_prior": "true camera + 5 km, true attitude",
        "fix_method": "6-DOF (attitude and position)" if six_dof else "known attitude",
        "altitude_km": round(r["altitude_km"], 3),
        "ground_sample_m": round(r["ground_sample_m"], 1),
        "landmarks_in_view": r["landmarks_in_view"],
        "detections": r["n_detections"],
        "fix": r["fix"],
    }
    if r["fix"]:
        names = [landmarks[li].name or landmarks[li].id for _, li in r["identified_pairs"]]
        result.update(
            landmarks=names,
            identified_correct=r["identified_correct"],
            rms_px=round(r["rms_px"], 2),
            error_km=round(r["error_km"], 3),
            error_horizontal_km=round(r["error_horizontal_km"], 3),
        )
        result["fix_position"] = {k: round(v, 6 if k != "altitude_m" else 1) for k, v in r["fix_position"].items()}
        if r.get("sigma_horizontal_km") is not None:  # the fix's own 1-sigma (fix.position_sigma_horizontal_m)
            result["sigma_horizontal_km"] = round(r["sigma_horizontal_km"], 4)
        if six_dof:  # the attitude it found, against the truth
            result["attitude_error_deg"] = round(r["attitude_error_deg"], 4)
        if "unrefined" in r:  # the fix before the appearance refinement
            result["error_unrefined_km"] = round(r["unrefined"]["error_km"], 3)
    else:
        result["reason"] = r["reason"]
    if patches:
        result["fix_source"] = r["fix_source"]
        result["patches"] = {k: v for k, v in r.get("patches", {}).items() if k != "identified_px"}

    dets = [Detection(*d) for d in r["detections_px"]]
    identified = dict(r["identified_pairs"]) if r["fix"] else {}
    listing = out.with_suffix(".json")
    write_detections(listing, image, detection_records(dets, identified, landmarks, r["matched"]))
    schema.atomic_write_bytes(out, annotate_frame(img, r, row, landmarks, dets))
    result.update(annotated=str(out), detections_file=str(listing))
    return result


def annotate_frame(image: np.ndarray, r: dict, row: dict, landmarks, dets) -> bytes:
    """The annotated PNG of :func:`navigate_rendered_frame`'s result ``r`` (its detections ``dets``) on the frame
    ``image`` (I/F, stretched to its 99.5th percentile)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse, Rectangle

    h, w = image.shape
    top = float(np.percentile(image, 99.5)) or 1.0
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.imshow(np.clip(image / top, 0.0, 1.0), cmap="gray", vmin=0.0, vmax=1.0)
    for lb in row["landmarks"]:
        e = lb["ellipse"]
        angle = np.degrees(e["angle_rad"])
        ax.add_patch(Ellipse((e["cu"], e["cv"]), 2 * e["a"], 2 * e["b"], angle=angle, fill=False, ec="#40c040", lw=0.5))
    draw_detections(ax, dets, r.get("identified_pairs", []), landmarks)
    for u, v, half in (r.get("patches") or {}).get("identified_px", []):  # the terrain patches that fixed it
        ax.add_patch(Rectangle((u - half, v - half), 2 * half, 2 * half, fill=False, ec="#30c0ff", lw=1.0))
    arrow = ""
    if r["fix"] and r.get("position_enu_m") is not None:
        arrow = error_arrow(ax, r, row)
    if r.get("fix_source") == "patches":
        title = (
            f"fix from {r['identified']} terrain patches (cyan), RMS {r['rms_px']:.1f} px; "
            f"error {r['error_km']:.2f} km (horizontal {r['error_horizontal_km']:.2f} km)"
        )
    elif r["fix"]:
        title = (
            f"fix: {len(r['identified_pairs'])} landmarks, RMS {r['rms_px']:.1f} px; error {r['error_km']:.2f} km "
            f"(horizontal {r['error_horizontal_km']:.2f} km)"
        )
        if "unrefined" in r:
            title += f"\nbefore the appearance refinement: {r['unrefined']['error_km']:.2f} km"
    else:
        title = f"no fix: {r['reason']}"
    if arrow:
        title += ("; " if "\n" in title else "\n") + arrow
    return png_of(fig, ax, w, h, f"{row['trajectory']} frame {row['index']}, {r['altitude_km']:.0f} km up: {title}")


# The error arrow is drawn at least this long (px): a fix tens of metres off is a fraction of a pixel.
MIN_ARROW_PX = 40.0


def error_arrow(ax, r: dict, row: dict) -> str:
    """Draw the fix's error on the frame: from the frame centre (where the true camera sees its boresight's
    ground point) to where the fixed camera would see that point, magnified to at least ``MIN_ARROW_PX``
    (by a 1-2-5 step, written beside its tip); returns the title's short caption."""
    lat0, lon0 = row["frame_origin"]["lat"], row["frame_origin"]["lon"]
    r_wc, k = true_camera(row)
    r_fix = np.array(r["rotation_fix"], dtype=np.float64) if "rotation_fix" in r else r_wc  # a 6-DOF fix's own
    target = geometry.mc_to_enu(geometry.latlon_to_mc(row["pose"]["target_lat"], row["pose"]["target_lon"]), lat0, lon0)
    seen = {
        name: project_pinhole(target[None], rot, np.asarray(c, dtype=np.float64), k)[0]
        for name, c, rot in (("truth", row["camera_enu"]["position_m"], r_wc), ("fix", r["position_enu_m"], r_fix))
    }
    shift = seen["fix"] - seen["truth"]
    length = float(np.hypot(*shift))
    scale = 1.0
    if 0.0 < length < MIN_ARROW_PX:  # the smallest 1-2-5 step that makes it visible (at most 2.5 x the minimum)
        base = 10.0 ** math.floor(math.log10(MIN_ARROW_PX / length))
        scale = next(base * f for f in (1.0, 2.0, 5.0, 10.0) if length * base * f >= MIN_ARROW_PX)
    tip = seen["truth"] + scale * shift
    ax.annotate(
        "", xy=tuple(tip), xytext=tuple(seen["truth"]), arrowprops={"arrowstyle": "->", "color": "cyan", "lw": 2}
    )
    ax.text(*tip, f" error x{scale:g}" if scale > 1 else " error", color="cyan", fontsize=8, va="center")
    return f"arrow {length:.2f} px, x{scale:g}"
