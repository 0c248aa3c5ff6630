"""Direct (reference) mode: one Cycles render per image with the Hapke node material and the sun.

Channels:
- IF     = the Combined pass (Cycles integrates the Hapke-weighted Diffuse BSDF over the solar disk
           with its own shadow rays);
- N      = the Normal pass (world/ENU shading normal, averaged over the pixel's samples, renormalised);
- depth  = the Depth pass (distance along the view axis, metres; 1e10 where no terrain);
- lit    = Diffuse Direct / max(mu0, eps), clipped to [0, 1]. The Diffuse Direct pass is the
           direct irradiance <max(N.l, 0) V(l)>_disk without the BSDF colour, so dividing by the
           centre-of-disk mu0 gives the illuminated fraction of the solar disk (cosine weighted):
           1 lit, 0 in shadow, fractional in penumbra. No second render is needed.
"""

from __future__ import annotations

import numpy as np

LIT_MU0_EPS = 1e-6


def unit_normals(normal_pass: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(normal_pass, axis=-1, keepdims=True)
    return np.where(n > 1e-12, normal_pass / np.maximum(n, 1e-12), 0.0).astype(np.float32)


def render(session, item: dict, to_sun: np.ndarray) -> dict[str, np.ndarray]:
    session.set_sun(to_sun)
    # the host's per-render seed, when given: independent Monte-Carlo noise per image
    session.configure("hapke", session.cfg["samples"], seed=item.get("seed"))
    p = session.render_view(item)
    normals = unit_normals(p["Normal"])
    mu0 = normals @ np.asarray(to_sun, dtype=np.float32)
    diff_direct = p["Diffuse Direct"][..., 0]
    lit = np.where(mu0 > LIT_MU0_EPS, diff_direct / np.maximum(mu0, LIT_MU0_EPS), 0.0)
    return {
        "IF": p["Combined"][..., 0],
        "depth": p["Depth"],
        "N.X": normals[..., 0],
        "N.Y": normals[..., 1],
        "N.Z": normals[..., 2],
        "lit": np.clip(lit, 0.0, 1.0).astype(np.float32),
    }
