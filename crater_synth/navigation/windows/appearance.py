"""Landmark search by predicted appearance on map windows (``nav-eval nav/detector=appearance``).

The rendered-frame search (:mod:`.appearance`) predicts each map landmark as a lander's camera should
see it and finds it by normalised cross-correlation (NCC). A mosaic window is an orthographic nadir
frame of the polar stereographic map (:mod:`.frames`), so here each landmark's window
(:func:`.refine.window_terrain`: the DEM on the sphere, horizon-map shadows, far field towards the Sun)
is shaded with the project's Hapke model for a nadir view and placed in the frame through the prior
georeference (each sample's (lat, lon) -> map (x, y) -> pixel), then searched for as far as the prior's
uncertainty (``prior_sigma_km`` of :class:`.fix.FixParams`) plus ``margin_px``, coarse to fine
(:func:`.appearance.register_wide`). A peak of NCC >= ``min_ncc`` is a detection at the
landmark's rim circle moved by the shift; identification and fix are the detectors'
(:func:`.fix.fix_frame`), so a landmark found in the wrong place is an outlier the fix must reject.

The Sun. A mosaic has no image time. Its azimuth is the frozen light model's (:mod:`.light`: one local
azimuth per mosaic quadrant, pooled from image statistics, here the direction the light travels, so the
Sun lies opposite), turned into each landmark's own local frame. Its elevation is not known either: the
mosaic's images were taken over many orbits and the elevation changes with latitude. Each window tries
the ``sun_el_deg`` elevations and keeps the one whose predictions correlate best with the
window (the median peak NCC over the landmarks searched): image statistics under the prior, no truth.
The terrain of a window is read once per landmark and Sun azimuth (:meth:`.refine.Refiner.terrain`,
kept between frames); only the shading changes with the elevation.

What it cannot see: craters missing from the map (it looks only where the map and the prior say a
landmark is), so its detection precision is measured against the map's own landmarks.

Lost in space (:func:`confirmed_fix`), the places a crater vote offers take the prior's role: each is searched
(:func:`search_place`), and the window is fixed where the search confirms one.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from crater_core import geometry
from crater_synth.navigation.detectors.classical import Detection
from crater_synth.navigation.fix.appearance import blurred_frames, register_wide
from crater_synth.navigation.fix.lost_in_space import Candidate, LostInSpaceParams, confirm_places
from crater_synth.navigation.fix.patches import window_patches
from crater_synth.navigation.fix.refine import Refiner, lander_dem, shade_window
from crater_synth.navigation.fix.solve import Fix, fix_frame
from crater_synth.navigation.fix.terrain_places import mosaic_shaded_map, terrain_places
from crater_synth.navigation.georef import Georef, ground_distance_km, local_north_image_angle, stereo_forward
from crater_synth.terrain.dem import DemError

# The view of a mosaic window is nadir; a camera this far above the landmark sees every sample along its
# local vertical to within 1e-5 rad (the WAC's own view angles are not known per mosaic pixel).
NADIR_CAMERA_M = 1.0e7
# The terrain of a landmark's window depends on the Sun's azimuth only: it is computed (and kept) for a Sun
# at this elevation, and shaded at each elevation tried.
TERRAIN_SUN_EL_DEG = 10.0


@functools.lru_cache(maxsize=2)
def lander_refiner(pole: str, workers: int = 1):
    """The :class:`.refine.Refiner` (the pole's DEM stack and the Hapke model) the search predicts with;
    ``workers`` > 1 prepares a frame's new landmark windows in that many processes."""
    return Refiner(lander_dem(pole), workers=workers)


def sun_direction_mc(lat: float, lon: float, azimuth_rad: float, elevation_deg: float) -> np.ndarray:
    """Unit vector (MC) towards a Sun at local ``azimuth_rad`` (clockwise from local north) and
    ``elevation_deg`` above the local horizontal at (lat, lon)."""
    el = math.radians(elevation_deg)
    enu = np.array([math.cos(el) * math.sin(azimuth_rad), math.cos(el) * math.cos(azimuth_rad), math.sin(el)])
    return geometry.enu_basis(lat, lon).T @ enu


def window_detections(image, georef, landmarks, light_azimuth_rad: float, dparams, fparams, refiner):
    """(detections, chosen Sun elevation deg or None) of the map ``landmarks`` >= ``fparams.min_landmark_km``
    whose centre the prior ``georef`` places in ``image``, each searched for by its predicted appearance
    (module docstring). ``light_azimuth_rad``: local azimuth (clockwise from local north) the light
    travels along; ``refiner``: the :class:`.refine.Refiner` holding the DEM and the Hapke model."""
    frame = np.asarray(image, dtype=np.float64)
    height, width = frame.shape
    blurred = blurred_frames(frame)

    search = math.ceil(fparams.prior_sigma_km * 1000.0 / georef.pixel_m) + dparams.margin_px
    sun_az = light_azimuth_rad + math.pi
    elevations = tuple(dparams.sun_el_deg)
    found: list[list] = [[] for _ in elevations]  # per elevation: (landmark, shift, NCC, predicted pixel)
    in_view = []
    for lm in landmarks:
        if lm.diameter_km < fparams.min_landmark_km:
            continue
        u0, v0 = georef.xy_to_uv(lm.x_m, lm.y_m)
        if 0.0 <= u0 < width and 0.0 <= v0 < height:
            in_view.append((lm, sun_direction_mc(lm.lat, lm.lon, sun_az, TERRAIN_SUN_EL_DEG)))
    refiner.prepare(in_view)  # new landmark windows computed in the refiner's workers, if it has any
    for lm, terrain_sun in in_view:
        u0, v0 = georef.xy_to_uv(lm.x_m, lm.y_m)
        try:  # kept between frames under the same Sun azimuth (:meth:`.refine.Refiner.terrain`)
            terrain = refiner.terrain(lm, terrain_sun)
        except DemError:  # the window or its far field leaves the DEM: not searched
            continue
        camera = lm.position_mc() + NADIR_CAMERA_M * geometry.enu_basis(lm.lat, lm.lon)[2]
        uv = None
        for k, el in enumerate(elevations):
            sun = sun_direction_mc(lm.lat, lm.lon, sun_az, el)
            points, predicted = shade_window(terrain, sun, camera, refiner.hapke)
            if uv is None:
                lat, lon, _ = geometry.mc_to_latlon(points)
                uv = np.stack(georef.xy_to_uv(*stereo_forward(lat, lon, georef.pole)), axis=-1)
            shift, ncc = register_wide(frame, uv, predicted, search, dparams.coarse_steps, blurred, dparams.thin)
            found[k].append((lm, shift, ncc, (u0, v0)))
    if not any(found):
        return [], None

    def score(rows) -> float:
        return float(np.median([r[2] if r[1] is not None and np.isfinite(r[2]) else 0.0 for r in rows]))

    best = max(range(len(elevations)), key=lambda k: (score(found[k]), -k))
    dets = [
        Detection(u0 + shift[0], v0 + shift[1], lm.diameter_km * 500.0 / georef.pixel_m, float(ncc))
        for lm, shift, ncc, (u0, v0) in found[best]
        if shift is not None and ncc >= dparams.min_ncc
    ]
    return dets, elevations[best]


def window_patch_fix(image, prior, light_azimuth_rad: float, dparams, fparams, refiner, params):
    """(patches, detections, fix) of a map window navigated with its terrain patches (:mod:`.patches`,
    :func:`~.patches.window_patches` under the prior georeference ``prior``) instead of its craters: each
    patch searched for by its predicted appearance (:func:`window_detections`, the same Sun and settings as
    a crater), then the detectors' identification and fix (:func:`.fix.fix_frame`)."""
    patches = window_patches(refiner.dem, prior, np.shape(image), params)
    if not patches:
        return [], [], Fix(False, "no patch on the DEM")
    dets, _ = window_detections(image, prior, patches, light_azimuth_rad, dparams, fparams, refiner)
    return patches, dets, fix_frame(dets, patches, prior, np.shape(image), fparams)


def patch_truth_correct(dets, patches, inliers, truth, inlier_px: float) -> int:
    """How many of a patch fix's ``inliers`` ((detection, patch) index pairs) are identified correctly: the
    detection lies within ``inlier_px`` of where the true georeference ``truth`` places the patch's point
    (a patch is a place, not a crater: there is no rim to match)."""
    hits = 0
    for d, p in inliers:
        u, v = truth.xy_to_uv(patches[p].x_m, patches[p].y_m)
        hits += int(math.hypot(dets[d].u - float(u), dets[d].v - float(v)) <= inlier_px)
    return hits


def confirmed_fix(
    image,
    pole: str,
    pixel_m: float,
    cands: list[Candidate],
    landmarks,
    light: float,
    lis: LostInSpaceParams,
    dparams,
    fparams,
    valid=None,
    terrain=None,
) -> tuple[list, Fix]:
    """(the appearance search's detections, its fix) of a map window lost in space, its craters' candidates
    (:func:`.lost_in_space.lost_in_space_search`) confirmed by appearance (``lis.confirm``,
    :class:`.lost_in_space.LostInSpaceParams`): each place :func:`.lost_in_space.hypotheses` keeps, best first,
    becomes a north-up prior (the attitude's heading) searched within ``lis.confirm_reach_km``
    (:func:`search_place`, the appearance settings ``dparams``) and fixed with ``fparams``. ``light``: the
    image direction (radians) the light travels along, which the ephemeris and the attitude give whatever the
    place; each place predicts its landmarks under the local azimuth that direction has there. With
    ``lis.terrain_places`` the terrain's places (:func:`window_terrain_places`) are searched first, then the
    vote's more than ``lis.rival_km`` from them. The first
    confirmed place is the fix; a second confirmed place more than ``lis.rival_km`` from it makes it
    ambiguous: no fix. ``valid``: the image's pixels that are the window's (a turned frame's canvas has filled
    corners), for the terrain's correlation; ``terrain``: the terrain's places when already found (they depend
    on neither the candidates nor a light try's detections)."""
    if terrain is None:
        terrain = window_terrain_places(image, pole, pixel_m, light, lis, dparams, valid)
    places = confirm_places(terrain, cands, lis)
    if not places:
        return [], Fix(False, lis.no_place_reason())
    confirmed: list[tuple[list, Fix]] = []
    refusals = []
    for _, centre, support in places:
        dets, fix = search_place(image, pole, pixel_m, centre, landmarks, light, lis, dparams, fparams)
        if fix.ok:
            fix.support = support
            confirmed.append((dets, fix))
        else:
            refusals.append(fix.reason)
    if not confirmed:  # its support says a place was searched (the best's, as a lost-in-space refusal carries)
        refused = Fix(False, f"no place confirmed by appearance ({len(places)} searched; the best: {refusals[0]})")
        refused.support = places[0][2]
        return [], refused
    dets, fix = confirmed[0]
    for _, other in confirmed[1:]:
        km = float(ground_distance_km(fix.x_m, fix.y_m, other.x_m, other.y_m, pole))
        if km > lis.rival_km:
            n = f"{len(fix.inliers)} and {len(other.inliers)} landmarks"
            return [], Fix(False, f"ambiguous: appearance confirms places {km:.0f} km apart ({n})")
    return dets, fix


def window_terrain_places(
    image, pole: str, pixel_m: float, light: float, lis, dparams, valid=None
) -> list[tuple[complex, float]]:
    """The ``lis.terrain_places`` map points under the window's centre (with their correlation) where the window
    best matches the lander's DEM shaded as a mosaic shows it (:func:`.terrain_places.mosaic_shaded_map`): lit
    from the direction opposite ``light`` (the image direction the light travels; a window's +u is the map's
    +x, its +v the map's -y) at each of ``dparams.sun_el_deg`` above every point's horizon, the best places of
    all elevations, at least twice ``lis.confirm_reach_km`` apart; ``valid``: the pixels correlated (all finite
    ones when None)."""
    if not lis.terrain_places:
        return []
    frame = np.asarray(image, dtype=np.float32)
    valid = np.isfinite(frame) if valid is None else np.asarray(valid, dtype=bool) & np.isfinite(frame)
    frame = np.where(valid, frame, np.float32(np.median(frame[valid]) if valid.any() else 0.0))
    sun_map_deg = -math.degrees(light + math.pi)
    centre = (frame.shape[1] / 2.0, frame.shape[0] / 2.0)
    apart = 2.0 * lis.confirm_reach_km
    found: list[tuple[complex, float]] = []
    for el in dparams.sun_el_deg:
        shaded = mosaic_shaded_map(pole, lis.terrain_pixel_m, sun_map_deg, float(el))
        found += terrain_places(frame, valid, pixel_m, centre, 0.0, shaded, lis.terrain_places, apart)
    kept: list[tuple[complex, float]] = []
    for place in sorted(found, key=lambda p: -p[1]):
        if all(abs(place[0] - k[0]) > apart * 1000.0 for k in kept):
            kept.append(place)
    return kept[: lis.terrain_places]


def search_place(image, pole: str, pixel_m: float, centre: complex, landmarks, light: float, lis, dparams, fparams):
    """(detections, fix) of the appearance search around one place (map point ``centre`` as x + iy under the
    frame centre), north-up, within ``lis.confirm_reach_km``, under the local azimuth the light's image
    direction ``light`` has there; the fix needs ``lis.confirm_min_landmarks`` landmarks (at least ``fparams``'
    own minimum)."""
    reach = lis.confirm_params(fparams)
    shape = np.shape(image)
    prior = Georef.centred_on(pole, centre.real, centre.imag, shape, pixel_m)
    alpha = light - float(local_north_image_angle(centre.real, centre.imag, pole))
    dets, _ = window_detections(image, prior, landmarks, alpha, dparams, reach, lander_refiner(pole))
    return dets, fix_frame(dets, landmarks, prior, shape, reach)
