"""An on-board DEM with a known error: how much the appearance search and the terrain patches depend on it.

The appearance search (:mod:`.appearance`), the refinement (:mod:`.refine`) and the terrain patches
(:mod:`.patches`) predict a frame from the DEM the lander carries. Rendered frames come from that same DEM
(with sub-DEM detail added), so they cannot show what an error of the DEM costs. :class:`PerturbedDem`
gives the lander a DEM with a smooth, seeded height error (``nav-frames-eval --dem-error-m``): the frames
stay as rendered, the prediction, the patches' 3-D points and the fix use the erroneous heights.

The error is a sum of plane waves of random directions and phases in the polar stereographic plane, with
wavelengths spread over a factor of four around ``wavelength_km`` (a stationary field of that scale and
RMS ``rms_m``): the kind of error a gridded altimetry DEM has between its tracks. It is a model for a
sensitivity analysis, not a description of LOLA's error.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from crater_synth.navigation.georef import stereo_forward

WAVES = 16  # plane waves in the field: enough for a field that looks random at a few wavelengths


@dataclasses.dataclass(frozen=True)
class DemErrorParams:
    """The on-board DEM's height error: RMS (m) and central wavelength (km)."""

    rms_m: float
    wavelength_km: float = 5.0

    def __post_init__(self):
        if not 0.0 <= float(self.rms_m) <= 1000.0:
            raise ValueError(f"DEM error rms_m={self.rms_m}: expected 0 to 1000 m")
        if not 0.5 <= float(self.wavelength_km) <= 500.0:
            raise ValueError(f"DEM error wavelength_km={self.wavelength_km}: expected 0.5 to 500 km")


class PerturbedDem:
    """``dem`` (a :class:`~crater_synth.terrain.dem.Dem` or stack) whose :meth:`sample` adds the seeded
    error field of ``params`` at ``pole``; everything else is ``dem``'s."""

    def __init__(self, dem, params: DemErrorParams, pole: str, seed: int = 0):
        rng = np.random.default_rng([seed, 13])
        direction = rng.uniform(0.0, 2.0 * math.pi, WAVES)
        wavelength = params.wavelength_km * 1000.0 * np.exp(rng.uniform(math.log(0.5), math.log(2.0), WAVES))
        self.dem, self.params, self.pole = dem, params, pole
        self._k = np.column_stack([np.cos(direction), np.sin(direction)]) * (2.0 * math.pi / wavelength)[:, None]
        self._phase = rng.uniform(0.0, 2.0 * math.pi, WAVES)
        self._amplitude = params.rms_m * math.sqrt(2.0 / WAVES)  # random phases: RMS of the sum = rms_m

    def error_m(self, lat_deg, lon_deg) -> np.ndarray:
        """The height error (m) at (lat, lon)."""
        x, y = stereo_forward(np.asarray(lat_deg, float), np.asarray(lon_deg, float), self.pole)
        arg = np.multiply.outer(np.asarray(x), self._k[:, 0]) + np.multiply.outer(np.asarray(y), self._k[:, 1])
        return self._amplitude * np.cos(arg + self._phase).sum(axis=-1)

    def sample(self, lat_deg, lon_deg, **kw):
        """``dem.sample`` with the error added to its heights."""
        result = self.dem.sample(lat_deg, lon_deg, **kw)
        lat, lon = np.broadcast_arrays(np.asarray(lat_deg, float), np.asarray(lon_deg, float))
        return dataclasses.replace(result, heights=result.heights + self.error_m(lat, lon))

    def __getattr__(self, name):
        if name.startswith("__") or name in ("dem", "params", "pole"):  # not yet set (unpickling)
            raise AttributeError(name)
        return getattr(self.dem, name)
