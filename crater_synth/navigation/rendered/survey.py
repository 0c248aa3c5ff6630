"""Training frames for the learned crater detector: short nadir survey tracks rendered by ``nav-frames``.

A learned detector must see what a polar camera sees: craters of every size under every low Sun. The
survey draws ``tracks`` short great-circle ground tracks over one pole's landmark map (midpoints spread
evenly in area between ``MIN_RADIUS_KM`` and ``MAX_RADIUS_KM`` from the pole, random headings), each with
its own physical Sun: a sub-solar latitude in the pole's summer half of the lunar obliquity and a local
hour angle drawn so that the Sun stands at least ``MIN_SUN_ELEVATION_DEG`` above both ends of the track.
Frames are near-orthographic nadir views (a narrow field of view from a high altitude, like a mosaic
window) at ``GROUND_SAMPLE_M``; the renderer, the terrain builder and the labels are those of
``crater-synth nav-frames`` (docs/navigation/rendered.md), so the detector is trained on
synthetic frames only. Every track is its own ``nav-frames`` directory (``DIR/track_NNN``); a track whose
manifest exists is skipped, so an interrupted survey resumes.

Only the south pole's DEM and map are used for training: the north is the detector's held-out test.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import click
import numpy as np

from crater_core import geometry, trajectory
from crater_synth.config import load_settings
from crater_synth.errors import UserError
from crater_synth.navigation.rendered.frames import frame_overrides, render_frames
from crater_synth.outfolder import OutFolder

GROUND_SAMPLE_M = 800.0  # twice the mosaic's 400 m/px: the detector's finest level (docs/navigation/rendered.md)
WIDTH_PX = 256
FOV_DEG = 20.0  # narrow: the ground sample varies by < 3 % across the frame, close to a map window
FRAMES_PER_TRACK = 4
TRACK_LENGTH_KM = 450.0
MIN_RADIUS_KM = 60.0  # polar cap left out: the mosaic's mixed-Sun cap is no evaluation window either
MAX_RADIUS_KM = 370.0  # a shared patch (+-230 km about two frames) stays inside the 1219 km DEM square
MIN_SUN_ELEVATION_DEG = 1.0
MAX_HOUR_ANGLE_DEG = 100.0
TRACK_DIR = re.compile(r"track_\d{3,}")
OBLIQUITY_DEG = 1.54  # lunar spin-axis obliquity to the ecliptic (crater_core/illumination.py)


def _altitude_km() -> float:
    """Altitude giving ``GROUND_SAMPLE_M`` at the frame centre with ``FOV_DEG`` over ``WIDTH_PX``."""
    return WIDTH_PX * GROUND_SAMPLE_M / (2.0 * math.tan(math.radians(FOV_DEG / 2.0))) / 1000.0


def _destination(lat: float, lon: float, heading_deg: float, distance_km: float) -> tuple[float, float]:
    """The point ``distance_km`` along the great circle leaving (lat, lon) at ``heading_deg`` (from north)."""
    p = geometry.latlon_to_mc(lat, lon) / geometry.MOON_RADIUS_M
    east, north, _ = geometry.enu_basis(lat, lon)
    h = math.radians(heading_deg)
    t = math.cos(h) * north + math.sin(h) * east
    ang = distance_km * 1000.0 / geometry.MOON_RADIUS_M
    q = math.cos(ang) * p + math.sin(ang) * t
    la, lo, _ = geometry.mc_to_latlon(q * geometry.MOON_RADIUS_M)
    return float(la), float(lo)


def plan_tracks(n_tracks: int, seed: int = 0, pole: str = "south") -> list[dict]:
    """``n_tracks`` seeded survey tracks: each a dict of ``trajectory.*`` values for ``nav-frames``."""
    if n_tracks < 1:
        raise UserError(f"--tracks {n_tracks}: must be >= 1")
    sign = -1.0 if pole == "south" else 1.0
    alt = _altitude_km()
    out = []
    for t in range(n_tracks):
        rng = np.random.default_rng([seed, t])
        for _attempt in range(1000):
            rho = math.sqrt(rng.uniform(MIN_RADIUS_KM**2, MAX_RADIUS_KM**2))
            colat = math.degrees(rho * 1000.0 / geometry.MOON_RADIUS_M)
            mid = (sign * (90.0 - colat), float(rng.uniform(0.0, 360.0)))
            heading = float(rng.uniform(0.0, 360.0))
            start = _destination(*mid, heading, -TRACK_LENGTH_KM / 2.0)
            end = _destination(*mid, heading, TRACK_LENGTH_KM / 2.0)
            if max(90.0 - sign * start[0], 90.0 - sign * end[0]) > math.degrees(
                MAX_RADIUS_KM * 1000.0 / geometry.MOON_RADIUS_M
            ):
                continue
            sub_lat = sign * float(rng.uniform(0.0, OBLIQUITY_DEG))
            sub_lon = mid[1] - float(rng.uniform(-MAX_HOUR_ANGLE_DEG, MAX_HOUR_ANGLE_DEG))
            to_sun = trajectory.sun_direction_mc(sub_lat, sub_lon)
            els = [trajectory.sun_elevation_azimuth(to_sun, *p)[0] for p in (start, mid, end)]
            if min(els) >= MIN_SUN_ELEVATION_DEG:
                break
        else:  # pragma: no cover - the draw always succeeds for the polar bands above
            raise UserError(f"survey track {t}: no sunlit track found")
        out.append(
            {
                "name": f"detector_{pole}_{t:03d}",
                "start": [round(start[0], 5), round(start[1], 5)],
                "end": [round(end[0], 5), round(end[1], 5)],
                "altitude_km": [round(alt, 3), round(alt, 3)],
                "frames": FRAMES_PER_TRACK,
                "off_nadir_deg": 0.0,
                "off_nadir_azimuth_deg": 0.0,
                "fov_deg": FOV_DEG,
                "width_px": WIDTH_PX,
                "sun": "physical",
                "subsolar_lat_deg": round(sub_lat, 4),
                "subsolar_lon_deg": round(sub_lon % 360.0, 4),
            }
        )
    return out


def track_overrides(track: dict) -> list[str]:
    """The Hydra overrides that select ``track`` on top of ``configs/trajectory/polar_orbit_arc.yaml``."""
    return ["trajectory=polar_orbit_arc"] + [f"trajectory.{k}={json.dumps(v)}" for k, v in track.items()]


def track_dirs(root: Path) -> list[Path]:
    """The rendered track directories under ``root`` (those holding a manifest), in name order."""
    return sorted(p.parent for p in Path(root).glob("track_*/manifest.jsonl"))


def render_survey(
    out: Path, n_tracks: int, seed: int = 0, overrides: tuple[str, ...] = (), progress: bool = True
) -> dict:
    """Render the survey's tracks into ``out/track_NNN`` (skipping finished ones); returns a summary.

    ``out`` is a ``navdetector-survey`` folder (crater_synth.outfolder) of this ``seed``: another kind's
    folder, another seed's survey, or a file outside the tracks' folders is refused before anything is
    rendered; each track's folder is a ``nav-frames`` folder of its own trajectory."""
    out = Path(out)
    tracks = plan_tracks(n_tracks, seed)
    folder = OutFolder(out, "navdetector-survey", subject=f"seed={seed}", flag="--out")
    folder.check_clean(lambda n: "/" in n and TRACK_DIR.fullmatch(n.split("/", 1)[0]) is not None)
    done = rendered = 0
    with folder:
        for t, track in enumerate(tracks):
            d = out / f"track_{t:03d}"
            if (d / "manifest.jsonl").exists():
                done += 1
                continue
            settings = load_settings(frame_overrides(track_overrides(track) + list(overrides)))
            render_frames(settings, d, progress=False)
            folder.published()
            rendered += 1
            if progress:
                click.echo(f"track {t + 1}/{n_tracks} rendered ({track['name']})", err=True)
    return {"out_dir": str(out), "tracks": n_tracks, "rendered": rendered, "already_there": done, "seed": seed}
