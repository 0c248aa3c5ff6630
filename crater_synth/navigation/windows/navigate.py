"""``crater-synth navigate IMAGE``: detections, identification, fix and an annotated PNG for one frame.

The frame is a north-up polar-stereographic nadir view (e.g. a mosaic window written by
:func:`write_window`). Its sidecar ``IMAGE.geo.json`` (pole, left_m, top_m, pixel_m) is the truth;
``--prior LAT,LON`` the coarse position (default: the truth centre moved by 5 km, as in ``nav-eval``).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path

import cv2
import numpy as np

from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.patches import PATCH_SOURCE, PatchParams
from crater_synth.navigation.fix.solve import fix_frame
from crater_synth.navigation.frame_file import sidecar
from crater_synth.navigation.georef import Frame, Georef, ground_distance_km, local_north_image_angle
from crater_synth.navigation.output import draw_detections, png_of
from crater_synth.navigation.protocol import HEADLINE_MIN_D_KM, catalogue_split
from crater_synth.navigation.windows.appearance import lander_refiner, window_detections, window_patch_fix


# --------------------------------------------------------------------------------------------
# navigate IMAGE
# --------------------------------------------------------------------------------------------
def write_window(path: Path, frame: Frame) -> None:
    """A frame as PNG plus its ``.geo.json`` sidecar (what ``navigate`` reads)."""
    atomic_write_bytes(path, _png_gray(frame.image))
    atomic_write_text(sidecar(path), json.dumps(frame.georef.as_dict()) + "\n")


def _png_gray(img: np.ndarray) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    plt.imsave(buf, img, cmap="gray", vmin=0, vmax=255, format="png")
    return buf.getvalue()


def annotate(image, dets, landmarks, fix, prior: Georef | None, truth: Georef | None) -> bytes:
    """Annotated PNG: detections (red), identified landmarks with names (yellow), error arrow (cyan).
    ``prior`` (None for a lost-in-space fix) is not drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = image.shape
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.imshow(image, cmap="gray")
    draw_detections(ax, dets, fix.inliers if fix.ok else [], landmarks)
    patch_fix = fix.ok and landmarks[fix.inliers[0][1]].source == PATCH_SOURCE
    what = "terrain patches (cyan)" if patch_fix else "landmarks"
    title = "no fix: " + fix.reason if not fix.ok else f"fix: {len(fix.inliers)} {what}, RMS {fix.rms_px:.1f} px"
    if fix.ok and truth is not None:
        tu, tv = truth.xy_to_uv(fix.x_m, fix.y_m)
        ax.annotate("", xy=(tu, tv), xytext=(w / 2, h / 2), arrowprops={"arrowstyle": "->", "color": "cyan", "lw": 2})
        err = float(ground_distance_km(fix.x_m, fix.y_m, *truth.uv_to_xy(w / 2, h / 2), truth.pole))
        title += f"; error {err:.2f} km (arrow: truth centre -> fix, x1)"
    return png_of(fig, ax, w, h, title)


# The circles of :func:`annotate_catalogue`, by the parts of :func:`.protocol.catalogue_split`.
CATALOGUE_COLOURS = {"found": "#30e030", "missed": "#ff3030", "false": "#ff9a00"}
CATALOGUE_LABELS = {
    "found": "catalogue craters found",
    "missed": "catalogue craters missed",
    "false": "false detections",
}


def catalogue_circles(row: dict, dets, listed, georef: Georef) -> dict[str, list[tuple[float, float, float]]]:
    """(u, v, r) px of each part of a window's :func:`.protocol.catalogue_split`: the catalogued craters found
    and missed at their catalogue circles, the false detections at theirs. ``row``: the window's
    :func:`.evaluate.score_window` row with the catalogue ``listed``; ``dets`` its detections."""
    split = catalogue_split(row)
    out = {}
    for key in ("found", "missed"):
        craters = [listed[row["catalogue"][k]] for k in split[key]]
        u, v = georef.xy_to_uv(np.array([c.x_m for c in craters]), np.array([c.y_m for c in craters]))
        r = np.array([c.diameter_km for c in craters]) * 500.0 / georef.pixel_m
        out[key] = [(float(a), float(b), float(c)) for a, b, c in zip(u, v, r, strict=True)]
    out["false"] = [(dets[k].u, dets[k].v, dets[k].r) for k in split["false"]]
    return out


def annotate_catalogue(image, circles: dict, title: str) -> bytes:
    """Annotated PNG of a window against the crater catalogue (``circles``: :func:`catalogue_circles`):
    catalogued craters of D >= 15 km found (green) and missed (red), false detections of D >= 15 km
    (orange); the legend gives the three counts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle

    h, w = image.shape
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.imshow(image, cmap="gray")
    handles = []
    for key, colour in CATALOGUE_COLOURS.items():
        for u, v, r in circles[key]:
            ax.add_patch(Circle((u, v), r, fill=False, ec=colour, lw=1.4))
        label = f"{CATALOGUE_LABELS[key]} (D >= {HEADLINE_MIN_D_KM:g} km): {len(circles[key])}"
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec=colour, mew=1.5, ms=10, label=label))
    ax.legend(handles=handles, loc="lower right", fontsize=8, framealpha=0.85)
    return png_of(fig, ax, w, h, title)


# --------------------------------------------------------------------------------------------
# A frame that is not north-up (navigate --heading)
# --------------------------------------------------------------------------------------------
def turned_north_up(img: np.ndarray, truth: Georef | None, heading_deg: float):
    """(the frame turned north-up, its georeference, the 2 x 3 map of image to turned pixels) of a frame whose
    up points ``heading_deg`` clockwise from the map's up. The frame is turned about its centre onto a canvas
    that holds all of it (:func:`cv2.warpAffine`, bilinear), the corners filled with its median, which the
    detectors' normalisation reads as flat ground. ``truth`` (the ``.geo.json`` of the frame turned north-up:
    the same centre and pixel size) becomes the canvas's, about the same centre."""
    h, w = img.shape[:2]
    c, s = abs(math.cos(math.radians(heading_deg))), abs(math.sin(math.radians(heading_deg)))
    width, height = math.ceil(w * c + h * s - 1e-6), math.ceil(w * s + h * c - 1e-6)
    # cv2 turns counter-clockwise on the screen for a positive angle; the frame's content is the map turned
    # counter-clockwise by the heading, so it is turned back clockwise. cv2's pixel centres are at integers.
    turn = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), -heading_deg, 1.0)
    turn[:, 2] += ((width - w) / 2.0, (height - h) / 2.0)
    fill = float(np.median(img))
    flags = {"flags": cv2.INTER_LINEAR, "borderMode": cv2.BORDER_CONSTANT, "borderValue": fill}
    canvas = cv2.warpAffine(np.asarray(img, dtype=np.float32), turn, (width, height), **flags)
    if truth is not None:
        truth = Georef.centred_on(truth.pole, *truth.uv_to_xy(w / 2.0, h / 2.0), canvas.shape, truth.pixel_m)
    return canvas, truth, turn


def turned_back(dets: list[Detection], turn: np.ndarray) -> list[Detection]:
    """Detections on the canvas of :func:`turned_north_up` in the given frame's pixels (from the top-left
    corner, as every detection; cv2's from the pixel centre)."""
    if not dets:
        return []
    back = cv2.invertAffineTransform(turn)
    uv = np.array([(d.u - 0.5, d.v - 0.5) for d in dets]) @ back[:, :2].T + back[:, 2] + 0.5
    return [dataclasses.replace(d, u=float(u), v=float(v)) for d, (u, v) in zip(dets, uv, strict=True)]


def turned_footprint(turn: np.ndarray, shape, canvas_shape) -> np.ndarray:
    """The pixels of :func:`turned_north_up`'s canvas (``canvas_shape``) that the given frame of ``shape``
    covers (True), not its filled corners: a correlation's mask."""
    ones = np.ones(shape[:2], dtype=np.uint8)
    size = (int(canvas_shape[1]), int(canvas_shape[0]))
    return cv2.warpAffine(ones, turn, size, flags=cv2.INTER_NEAREST, borderValue=0).astype(bool)


def inside_frame(dets: list[Detection], border_r: float, turn: np.ndarray, shape) -> list[Detection]:
    """The detections on the canvas of :func:`turned_north_up` whose centre lies inside the given frame of
    ``shape`` by at least ``border_r`` x r: the detectors' border rule (:func:`.detectors.classical.detect`)
    held to the frame's edges, not the canvas's, so that nothing is found in the filled corners."""
    h, w = shape[:2]
    back = turned_back(dets, turn)
    return [d for d, b in zip(dets, back, strict=True) if min(b.u, w - b.u, b.v, h - b.v) >= border_r * d.r]


def appearance_window_fix(img, prior_g: Georef, landmarks, light: float, sun_elevation, dparams, fparams, patches):
    """(detections, light, fix, the landmarks the fix indexes, "craters" or "patches") of the appearance search
    (:mod:`.appearance`) on a map window: the light's image direction ``light`` (radians) turned into
    its local azimuth at the prior's frame centre; with ``patches``, a window its craters do not fix is
    navigated with its terrain patches (:func:`.appearance.window_patch_fix`)."""
    h, w = img.shape[:2]
    alpha = light - float(local_north_image_angle(*prior_g.uv_to_xy(w / 2, h / 2), prior_g.pole))
    if sun_elevation is not None:
        dparams = dataclasses.replace(dparams, sun_el_deg=(float(sun_elevation),))
    refiner = lander_refiner(prior_g.pole)
    dets, _ = window_detections(img, prior_g, landmarks, alpha, dparams, fparams, refiner)
    fix = fix_frame(dets, landmarks, prior_g, img.shape, fparams)
    if patches and not fix.ok:
        found, patch_dets, patch_fix = window_patch_fix(img, prior_g, alpha, dparams, fparams, refiner, PatchParams())
        if patch_fix.ok:
            return patch_dets, light, patch_fix, found, "patches"
    return dets, light, fix, landmarks, "craters"
