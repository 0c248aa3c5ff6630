"""Scale-space helpers shared by the crater detectors (:mod:`.classical`, :mod:`.template`): the padded
frame's spectrum, Gaussian filtering and derivatives on decimated grids, and sub-pixel local maxima."""

from __future__ import annotations

import math

import numpy as np

PAD_PX = 64  # reflected border around the frame before the FFT (the filters' edge effects stay outside)
PAD_MULTIPLE = 64  # padded size a multiple of this, so every decimated grid is whole


def spectrum(a: np.ndarray):
    from scipy import fft

    h, w = a.shape
    hp = -(-(h + 2 * PAD_PX) // PAD_MULTIPLE) * PAD_MULTIPLE
    wp = -(-(w + 2 * PAD_PX) // PAD_MULTIPLE) * PAD_MULTIPLE
    p = np.pad(a, ((PAD_PX, hp - h - PAD_PX), (PAD_PX, wp - w - PAD_PX)), mode="reflect")
    return fft.rfft2(p, workers=-1), p.shape


def decimation(sigma: float) -> int:
    """Grid step for a filter of scale sigma: a power of two <= sigma / 3 (the Gaussian has < 1e-3 of its
    transfer beyond the decimated grid's Nyquist frequency), at most 16."""
    return int(min(16, 2 ** max(0, math.floor(math.log2(max(sigma / 3.0, 1.0))))))


def filtered(spec, shape, sigma: float, step: int, du: float | None = None, dv: float | None = None) -> np.ndarray:
    """G_sigma * I (``du`` None) or sigma x d . grad (G_sigma * I) for unit d = (du, dv), on the padded
    grid decimated by ``step`` (the spectrum cropped to the decimated grid's band: one small inverse FFT)."""
    from scipy import fft

    hp, wp = shape
    hs, ws = hp // step, wp // step
    rows = np.r_[0 : hs // 2, hp - hs // 2 : hp]
    sub = spec[rows, : ws // 2 + 1]
    ku = 2.0 * np.pi * fft.rfftfreq(ws)[None, :] / step
    kv = 2.0 * np.pi * fft.fftfreq(hs)[:, None] / step
    transfer = np.exp(-0.5 * sigma * sigma * (ku * ku + kv * kv))
    if du is None:
        return fft.irfft2(sub * transfer, s=(hs, ws), workers=-1) / (step * step)
    transfer = 1j * (ku * du + kv * dv) * transfer
    return sigma * fft.irfft2(sub * transfer, s=(hs, ws), workers=-1) / (step * step)


def peaks(resp: np.ndarray, threshold: float):
    """Local maxima (3 x 3) above ``threshold`` with a sub-pixel (parabolic) position: (row, col, value)."""
    from scipy.ndimage import maximum_filter

    pk = (resp == maximum_filter(resp, size=3, mode="nearest")) & (resp >= threshold)
    pk[0, :] = pk[-1, :] = pk[:, 0] = pk[:, -1] = False
    i, j = np.nonzero(pk)
    c = resp[i, j]
    d2i = np.minimum(resp[i - 1, j] - 2.0 * c + resp[i + 1, j], -1e-9)  # < 0 at a maximum
    d2j = np.minimum(resp[i, j - 1] - 2.0 * c + resp[i, j + 1], -1e-9)
    di = 0.5 * (resp[i - 1, j] - resp[i + 1, j]) / d2i
    dj = 0.5 * (resp[i, j - 1] - resp[i, j + 1]) / d2j
    return i + np.clip(di, -0.5, 0.5), j + np.clip(dj, -0.5, 0.5), c
