"""The light direction handed to the detectors on real mosaic windows (docs/navigation/detectors.md).

A mosaic window carries no image time, so the light's direction comes from image statistics:
``nav.detector.light_scope`` "frame" (estimated on the window alone,
:func:`crater_synth.navigation.detectors.classical.detect`),
"quadrant" (one image-plane direction per mosaic quadrant, pooled over the south validation windows of
that quadrant: the second round's model, refuted by the test sectors) or "local" (one *local* azimuth,
clockwise from local north, per quadrant, sector or pole, pooled from the image statistics of that
unit's windows whatever their split, no truth used; in the map image it turns with each window's
longitude). "local" with ``light_seed_deg`` > 0 seeds the window's own estimate with it.
"""

from __future__ import annotations

import functools
import math

from crater_core.settings_nav import LightSettings
from crater_synth.errors import UserError
from crater_synth.navigation.detectors.classical import pooled_light_azimuth
from crater_synth.navigation.georef import Frame, local_north_image_angle
from crater_synth.navigation.windows.mosaic import windows


@functools.lru_cache(maxsize=8)
def quadrant_light(pole: str, quadrant: int, dparams: LightSettings) -> float:
    """Light direction of one mosaic quadrant (one Sun per quadrant, docs/navigation/overview.md), pooled over the
    *validation* windows of that quadrant only (its even sector), so no test pixel sets it."""
    frames = [f for f in windows("validation", pole) if f.sector // 2 == quadrant]
    if not frames:
        raise UserError(f"no validation window in quadrant {quadrant} of the {pole} mosaic")
    return pooled_light_azimuth([f.image for f in frames[::2]], dparams)


LOCAL_POOL_EVERY = 2  # every 2nd window of a quadrant or sector is pooled (the windows overlap: stride 64 px)
LOCAL_POOL_AZIMUTHS = 72  # 5-degree grid of local azimuths


def pool_windows(pole: str, pool: str, index: int) -> list[Frame]:
    """The windows of ``pole`` whose local light azimuth is pooled together: every window of mosaic
    quadrant ``index`` (``pool`` "quadrant"), of 45-degree sector ``index`` ("sector") or of the whole
    mosaic ("pole", index 0), whatever its split, every :data:`LOCAL_POOL_EVERY`-th. Only their pixels are
    used (image statistics, no landmark, no truth)."""
    keys = {"quadrant": lambda f: f.sector // 2, "sector": lambda f: f.sector, "pole": lambda f: 0}
    if pool not in keys:
        raise UserError(f"nav.detector.light_pool={pool!r}: expected one of {sorted(keys)}")
    key = keys[pool]
    frames = [f for f in windows(None, pole) if key(f) == index][::LOCAL_POOL_EVERY]
    if not frames:
        raise UserError(f"no window in {pool} {index} of the {pole} mosaic")
    return frames


@functools.lru_cache(maxsize=32)
def local_light(pole: str, pool: str, index: int, light: LightSettings) -> float:
    """Local azimuth (radians, clockwise from local north) of the light in one mosaic quadrant or sector of
    ``pole``: the tail scores of :func:`pool_windows` pooled in each window's local (east, north) frame
    (:func:`crater_synth.navigation.detectors.classical.pooled_light_azimuth` with each window's local-north image
    angle at its centre as rotation). A Sun at one local azimuth (images taken at similar local solar
    times) turns with longitude in the map image; this model follows it."""
    frames = pool_windows(pole, pool, index)
    rot = [float(local_north_image_angle(*f.centre_xy, pole)) for f in frames]
    return pooled_light_azimuth([f.image for f in frames], light, rotations=rot, n_azimuths=LOCAL_POOL_AZIMUTHS)


def frame_local_light(frame: Frame, dparams: LightSettings) -> float:
    """The local azimuth (radians, clockwise from local north) the light travels along in ``frame`` under
    the "local" light model (:func:`local_light` of the frame's quadrant, sector or pole)."""
    index = {"quadrant": frame.sector // 2, "sector": frame.sector, "pole": 0}[dparams.light_pool]
    return local_light(frame.georef.pole, dparams.light_pool, index, dparams.light())


def frame_light(frame: Frame, dparams: LightSettings) -> dict:
    """The light arguments of :func:`detect` for a mosaic window: ``light_dir`` (None: estimate on the
    frame) and ``light_prior`` ((direction, half-width) radians restricting the frame's estimate, or None)."""
    if dparams.light_scope == "frame":
        return {"light_dir": None, "light_prior": None}
    if dparams.light_scope == "quadrant":
        return {
            "light_dir": quadrant_light(frame.georef.pole, frame.sector // 2, dparams.light()),
            "light_prior": None,
        }
    if dparams.light_scope == "local":
        pole = frame.georef.pole
        alpha = frame_local_light(frame, dparams)
        theta = float((local_north_image_angle(*frame.centre_xy, pole) + alpha) % (2.0 * math.pi))
        if dparams.light_seed_deg > 0:
            return {"light_dir": None, "light_prior": (theta, math.radians(dparams.light_seed_deg))}
        return {"light_dir": theta, "light_prior": None}
    raise UserError(f"nav.detector.light_scope={dparams.light_scope!r}: expected 'frame', 'quadrant' or 'local'")
