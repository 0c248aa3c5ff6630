"""Sequential navigation along a trajectory: each frame's position prior from the last fix.

A lander does not navigate each frame from scratch: between two frames its inertial measurement unit
(IMU) carries the last fix forward. The prior of a frame is then the last fix moved by the motion since
(here the trajectory's true motion plus a dead-reckoning error that grows with the distance travelled, in
a seeded direction), and its uncertainty is that error's bound, not the 10 km of a frame navigated alone.
A tight prior lets the appearance search reach small landmarks and terrain patches it cannot search under
a 10 km prior (their windows would have to stay in the frame under every shift of the search).

The IMU is a model with two stated assumptions (``SequenceParams``), not a measured instrument: the
drift per distance travelled and the bound's factor. A wrong fix is carried forward like a right one: the
sequence does not hide it, the next frame's search under the tight prior then fails or agrees.
"""

from __future__ import annotations

import dataclasses
import math
import zlib

import numpy as np

from crater_core import geometry


@dataclasses.dataclass(frozen=True)
class SequenceParams:
    """The dead-reckoning model between fixes (assumptions, stated; not tuned)."""

    drift_share: float = 0.01  # IMU position error per distance travelled (1 %: a tactical-grade IMU over minutes)
    sigma_factor: float = 3.0  # the prior's bound: this many times the expected drift
    min_sigma_km: float = 1.0  # never tighter: the last fix's own error and the DEM's 1600 m pixels

    def __post_init__(self):
        if not 0.0 <= float(self.drift_share) <= 0.2:
            raise ValueError(f"sequence drift_share={self.drift_share}: expected 0 to 0.2")
        if not 1.0 <= float(self.sigma_factor) <= 10.0:
            raise ValueError(f"sequence sigma_factor={self.sigma_factor}: expected 1 to 10")
        if not 0.05 <= float(self.min_sigma_km) <= 50.0:
            raise ValueError(f"sequence min_sigma_km={self.min_sigma_km}: expected 0.05 to 50 km")


def frame_point_mc(row: dict, enu_m) -> np.ndarray:
    """A point given in ``row``'s frame ENU (m), Moon-centred."""
    o = row["frame_origin"]
    return geometry.enu_to_mc(np.asarray(enu_m, dtype=np.float64)[None], o["lat"], o["lon"])[0]


def last_fix(row: dict, result: dict) -> dict:
    """What the next frame's prior needs from a fixed frame: the fix and the true camera, Moon-centred."""
    return {
        "fix_mc": frame_point_mc(row, result["position_enu_m"]),
        "true_mc": frame_point_mc(row, row["camera_enu"]["position_m"]),
    }


def propagated_prior(row: dict, last: dict, params: SequenceParams, seed: int, default_sigma_km: float):
    """(prior centre in ``row``'s frame ENU (m), prior uncertainty km) carried from ``last`` (:func:`last_fix`)
    to ``row`` by the true motion plus a seeded drift of ``drift_share`` x the distance travelled; None
    when that uncertainty is no tighter than ``default_sigma_km`` (the frame is navigated alone)."""
    true_mc = frame_point_mc(row, row["camera_enu"]["position_m"])
    travelled = float(np.linalg.norm(true_mc - last["true_mc"]))
    sigma_km = max(params.min_sigma_km, params.sigma_factor * params.drift_share * travelled / 1000.0)
    if sigma_km >= default_sigma_km:
        return None
    o = row["frame_origin"]
    rng = np.random.default_rng([seed, 11, zlib.crc32(f"{row['trajectory']}:{row['index']}".encode())])
    phi = rng.uniform(0.0, 2.0 * math.pi)
    drift_enu = params.drift_share * travelled * np.array([math.cos(phi), math.sin(phi), 0.0])
    moved_mc = last["fix_mc"] + (true_mc - last["true_mc"])
    prior = geometry.mc_to_enu(moved_mc[None], o["lat"], o["lon"])[0] + drift_enu
    return prior, sigma_km
