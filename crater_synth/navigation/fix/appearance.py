"""Landmark search by predicted appearance: the map's landmarks found in a frame without a crater detector.

A lander that knows its attitude, the Sun and its position to a few kilometres (the prior) can predict
how each map landmark in view should look, from the DEM the map was measured in
(:meth:`.refine.Refiner.predict`: Hapke shading and horizon-map shadows), and where it should be. Each
landmark the prior places in the frame is searched for around its predicted place by normalised
cross-correlation (NCC):

- the search reaches the prior's uncertainty (``prior_sigma_km`` of :class:`.fix.FixParams`, at the
  landmark's depth) plus ``margin_px``;
- coarse to fine: first a grid of about ``coarse_steps`` steps each way across the whole search, on the
  frame blurred to the step (sigma = step / 2, so the coarse samples do not alias), then around the best
  a 5 x 5 grid at half the step, and so on down to one pixel; a parabola through the last 3 x 3 gives
  the sub-pixel peak. A peak on the border of the first grid is refused (the landmark is not there);
- a peak of NCC below ``min_ncc`` gives no detection.

Each landmark found becomes a :class:`..detectors.classical.Detection` where a detector would report its rim ellipse
(the ellipse predicted from the prior, moved by the search's shift), with the NCC as its score. The
identification and the fix are then the detectors' own (:func:`..rendered.evaluate.evaluate_frame`: pairs
gated by the prior, RANSAC with at least three agreeing landmarks, the ambiguity test), so a landmark
found in the wrong place is an outlier the fix must reject, as a false detection is.

This needs what a real frame from a lander's camera has and a mosaic window has not: one exposure, a
known Sun and attitude. It is evaluated on rendered frames only (docs/navigation/rendered.md).
"""

from __future__ import annotations

import math

import numpy as np

from crater_core import geometry
from crater_core.settings_nav import AppearanceSettings
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.pose import project_pinhole
from crater_synth.navigation.fix.refine import (
    ncc_at_offsets,
    parabola_vertex,
    rim_ellipses,
    samples_in_reach,
    square_offsets,
)
from crater_synth.terrain.dem import DemError


def blurred_frames(frame: np.ndarray):
    """``blurred(step)``: ``frame`` blurred for a search grid of that step (Gaussian, sigma = step / 2, so
    the grid's samples do not alias; step 1 is the frame itself), each step computed once."""
    from scipy.ndimage import gaussian_filter

    cache: dict[int, np.ndarray] = {1: frame}

    def blurred(step: int) -> np.ndarray:
        if step not in cache:
            cache[step] = gaussian_filter(frame, step / 2.0)
        return cache[step]

    return blurred


def register_wide(
    image: np.ndarray, uv: np.ndarray, predicted: np.ndarray, search_px: int, coarse_steps: int, blurred, thin=False
):
    """(shift (du, dv) px, NCC) of ``predicted`` (values at pixels ``uv``, the convention of
    :func:`.refine.register`) in ``image`` within ``search_px``, coarse to fine (module docstring);
    ``blurred(step)`` is the frame blurred for a grid of that step. None when the first grid's peak lies
    on its border or fewer than 16 samples stay in the frame under every shift.

    ``thin``: a grid of step s > 1 px correlates only every k-th predicted sample each way, k the samples
    per s px (``predicted`` a 2-D window): on a frame blurred to the step the dropped samples add little,
    and the coarse grid costs k^2 times less."""
    inside = samples_in_reach(image.shape, uv, predicted, search_px)
    if inside is None:
        return None, float("nan")
    thinned = {1: inside}

    def samples(step: int):
        if not thin or step == 1:
            return inside
        grid = np.asarray(uv, dtype=np.float64).reshape(*np.shape(predicted), 2)
        spacing = float(np.hypot(*(grid[0, 1] - grid[0, 0]))) or 1.0
        k = max(1, int(step / spacing))
        if k not in thinned:
            thinned[k] = samples_in_reach(image.shape, grid[::k, ::k], predicted[::k, ::k], search_px) or inside
        return thinned[k]

    step = max(1, math.ceil(search_px / coarse_steps))
    n = math.ceil(search_px / step)
    surf = ncc_at_offsets(blurred(step), *samples(step), square_offsets(np.zeros(2), n, step)).reshape(2 * n + 1, -1)
    i, j = np.unravel_index(int(np.argmax(surf)), surf.shape)
    if i in (0, 2 * n) or j in (0, 2 * n):
        return None, float(surf[i, j])
    centre = np.array([(j - n) * step, (i - n) * step], dtype=float)
    last = None  # the 5 x 5 one-pixel grid, when the last stage was one
    while step > 1:
        step = max(1, step // 2)
        surf = ncc_at_offsets(blurred(step), *samples(step), square_offsets(centre, 2, step)).reshape(5, -1)
        i, j = np.unravel_index(int(np.argmax(surf)), surf.shape)
        centre += np.array([(j - 2) * step, (i - 2) * step])
        last = (surf, i, j) if step == 1 else None
    u, v, p = inside
    if last is not None and 0 < last[1] < 4 and 0 < last[2] < 4:  # its 3 x 3 around the peak, already computed
        surf = last[0][last[1] - 1 : last[1] + 2, last[2] - 1 : last[2] + 2]
    else:
        surf = ncc_at_offsets(blurred(1), u, v, p, square_offsets(centre, 1, 1)).reshape(3, -1)
    i, j = np.unravel_index(int(np.argmax(surf)), surf.shape)
    if (i, j) != (1, 1):  # the peak moved a pixel: no parabola about the old centre
        return centre + np.array([j - 1, i - 1]), float(surf[i, j])
    return centre + np.array([parabola_vertex(*surf[1]), parabola_vertex(*surf[:, 1])]), float(surf[1, 1])


def appearance_detections(
    image, landmarks, points_enu, refiner, c_prior, r_wc, k, origin, to_sun_mc, search_km, params=None
):
    """Detections of the map ``landmarks`` (rim-centre points ``points_enu`` in the ENU frame of ``origin``
    (lat, lon)) that a camera at ``c_prior`` with world->camera rotation ``r_wc`` and intrinsics ``k`` (the
    convention of :func:`.fix.project_pinhole`) places in the frame ``image``, each searched for by its
    predicted appearance under the Sun ``to_sun_mc`` as far as ``search_km`` (the prior's uncertainty) at
    its depth (module docstring), with the search settings ``params`` (:class:`AppearanceSettings`);
    ``refiner``: the :class:`.refine.Refiner` holding the DEM and the Hapke
    model. Returns (detections, the predicted windows by landmark id, for the refinement to reuse)."""
    params = params or AppearanceSettings()
    lat0, lon0 = origin
    height, width = image.shape
    if not len(landmarks):
        return [], {}
    pts = np.asarray(points_enu, dtype=np.float64)
    depth = (pts - c_prior) @ r_wc[2]
    uv = np.full((len(pts), 2), np.nan)
    uv[depth > 0] = project_pinhole(pts[depth > 0], r_wc, c_prior, k)
    in_frame = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    cam_mc = geometry.enu_to_mc(c_prior, lat0, lon0)
    fov = math.degrees(2.0 * math.atan(0.5 * width / k[0, 0]))
    frame = np.asarray(image, dtype=np.float64)
    blurred = blurred_frames(frame)

    dets, windows = [], {}
    refiner.prepare([(landmarks[q], to_sun_mc) for q in np.nonzero(in_frame)[0]])  # in its workers, if any
    for q in np.nonzero(in_frame)[0]:
        lm = landmarks[q]
        try:
            win_mc, pred = refiner.predict(lm, to_sun_mc, cam_mc)
        except DemError:  # the window or its far field leaves the DEM: not searched
            continue
        windows[lm.id] = (win_mc, pred)
        win_uv = project_pinhole(geometry.mc_to_enu(win_mc.reshape(-1, 3), lat0, lon0), r_wc, c_prior, k)
        search = math.ceil(search_km * 1000.0 * k[0, 0] / depth[q]) + params.margin_px
        shift, ncc = register_wide(frame, win_uv, pred, search, params.coarse_steps, blurred)
        if shift is None or not ncc >= params.min_ncc:
            continue
        (rim,) = rim_ellipses(pts[q : q + 1], [lm.diameter_km * 500.0], c_prior, r_wc, fov, width)
        dets.append(Detection(rim.cu + shift[0], rim.cv + shift[1], rim.a, float(ncc)))
    return dets, windows
