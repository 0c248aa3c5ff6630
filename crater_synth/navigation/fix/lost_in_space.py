"""Lost-in-space identification: the position fix of a nadir frame with no position prior.

:func:`.fix.fix_frame` needs a prior position within ~10 km: landmarks predicted in the frame by the
prior are paired with detections. A lander that has lost its position has no such prior. Here the
frame's detections are matched against the whole landmark map by **crater pairs with diameters**:

* The frame is an orthographic nadir view of the map plane at a known pixel size (400 m/px for the
  mosaic windows; :mod:`.frames`), so a pair of craters is described, whatever the unknown heading
  and position, by its centre distance in km and the two diameters: invariant to rotation and
  translation, and the absolute scale is known (no scale invariance is needed).
* **Index**: every ordered pair of map landmarks (>= ``min_landmark_km``) closer than the frame's
  diagonal, sorted by distance (numpy sorting; :func:`build_index`, once per map).
* **Query**: every pair of the frame's ``n_detections`` largest detections (of those scoring at least
  ``vote_min_score``, when set: the sure tier of a detector's candidates) looks up the map pairs of
  the same distance (within ``dist_tol_px`` + ``dist_tol_r`` x the radii) whose diameters agree within
  ``radius_ratio``. Each such match defines one similarity pixel -> map (scale known, heading free),
  hence a frame-centre map point and a heading: a **vote** in a (x, y, heading) grid of ``bin_km`` x
  ``bin_km`` x ``bin_deg`` cells. A true solution collects votes from many pairs of correctly detected
  craters at one cell; a false pairing scatters.
* **Verification**: the ``n_verify`` best-voted cells each give a candidate transform (the mean of
  its votes); all detections, weak ones too, are paired with the landmarks it predicts in the frame
  (within ``gate_km``) and the existing RANSAC similarity fix (:func:`.fix.ransac_similarity`, scale and
  heading gated around the candidate) runs with the usual "no fix" rules (min inliers, disjoint rival
  inside the candidate, inlier RMS).
* **Ambiguity across the map** (strict: a false fix is worse than none): the best verified candidate
  is refused when another candidate whose frame centre lies more than ``rival_km`` away is supported by
  at least best - ``ambiguity_margin`` inliers (its consensus counted under its own transform, whether
  or not it reached ``min_inliers``). A repeated crater pattern therefore gives "no fix".
* **Candidate score** (``candidate_score``). ``inliers``: a candidate's support is its inlier count.
  ``significance`` (a contrario, as in the a-contrario RANSAC of Moisan and Stival 2004): its support is
  -log10 of the probability that chance alone puts that many of the frame's detections on the landmarks
  the candidate predicts (:func:`chance_log10`). A landmark is matched by chance when a detection of
  compatible radius (``fix.radius_ratio``) falls within its inlier tolerance anywhere in the frame, so the
  expected chance inliers are the sum over the predicted landmarks of 1 - exp(-n_compatible x tolerance
  disc / frame area); the count of chance inliers is taken as Poisson. Six inliers among a few large
  craters with few detections of their size are then strong evidence, six among many small ones weak,
  where the inlier count weighs both alike. The best candidate is kept only when its number of false
  alarms (``n_verify`` x that probability) is at most 10^``max_log10_nfa``, and a rival elsewhere within
  ``ambiguity_log10`` of its score makes the fix ambiguous. The model underestimates chance: on the north test
  windows this weighting made false fixes that inlier counts did not, and on validation windows moved so that
  they cannot be fixed chance reached 10^-8.5 heading-free, 10^-7.1 with the heading known, where the gate at
  0.01 false alarms asks 10^-4.1 (docs/navigation/fix.md). The ``attitude`` settings gate at 10^-7.6 with the
  heading known; the weighting is off by default.
* **The frame's own null** (``null_turns``, with the heading known): the frame's detections turned by quarter
  turns about its centre are searched too. At the attitude's heading a turned pattern cannot land on its true
  place, so what its best candidate reaches is chance on this frame's own craters, and the best candidate of the
  frame itself is kept only above it by ``null_margin_log10`` decades: a gate measured per frame, not set once for
  every frame.
* **Confirmation by appearance** (``confirm``): with the DEM on board, the candidates are hypotheses the
  appearance search confirms or not (:func:`hypotheses`; ``windows/appearance.py``), and the vote's own gate is
  not used.

Work is bounded: at most C(n_detections, 2) frame pairs, at most ``max_matches`` votes (the pairs of
smallest distance error kept), ``n_verify`` RANSAC runs. Settings (configs/nav/lost_in_space/) were chosen on
south windows only (docs/navigation/fix.md).

Length: one algorithm, the vote, its verification, the candidates' scores and the places a confirmation or its
chance test searches, sharing the pair index and the candidate type; split, each part would import the others.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import numpy as np

from crater_synth.navigation.fix.solve import (
    Fix,
    FixParams,
    apply_similarity,
    fit_similarity,
    inliers_of,
    ransac_similarity,
)

CANDIDATE_SCORES = ("inliers", "significance")
CONFIRMS = ("", "appearance")


@dataclass(frozen=True)
class LostInSpaceParams:
    """Settings of :func:`lost_in_space_fix` (chosen on south windows; docs/navigation/overview.md)."""

    n_detections: int = 30  # the frame's largest detections used for the pair votes
    min_landmark_km: float = 10.0  # landmarks indexed (and predicted in verification)
    max_pair_km: float = 290.0  # index pairs up to the 512 px frame's diagonal (205 km x sqrt 2)
    dist_tol_px: float = 2.0  # pair distance tolerance: px + dist_tol_r x (r_i + r_j)
    dist_tol_r: float = 0.15
    radius_ratio: float = 1.3  # detection / landmark radius within [1/x, x] for both craters
    bin_km: float = 8.0  # vote cell of the frame-centre map point
    bin_deg: float = 10.0  # vote cell of the heading
    max_matches: int = 200000
    n_verify: int = 8  # best-voted cells verified by the RANSAC fix
    gate_km: float = 4.0  # verification gate (+ r/4) around the landmarks a candidate predicts; chosen on south
    min_inliers: int = 6  # a lost-in-space fix needs more agreeing landmarks than a prior-gated one
    ambiguity_margin: int = 2  # a rival elsewhere with >= best - margin inliers: no fix
    rival_km: float = 5.0  # candidates whose centres are closer than this are the same solution
    # The attitude gives the frame's heading on the map (a north-up mosaic window: 0; a rendered frame: its
    # camera's): only votes within one heading cell of it count. On in the attitude settings only.
    known_heading: bool = False
    # With the heading known: each candidate takes that heading, and its fix may turn from it by at most this
    # (degrees; None: as far as a vote cell, bin_deg, from its votes' mean heading). True fixes of the south
    # validation windows come out within 1.2 degrees of a north-up window's heading, and chance transforms of
    # its mirror images up to 10 degrees off; yet at 2 degrees it removed no chance fix of them (other chance
    # transforms took their place), so it stays off.
    heading_tol_deg: float | None = None
    # Two tiers of detections (None: one). A pair vote needs two sure craters, or chance pairs of the many weak
    # candidates outvote the true ones; a candidate's transform, once voted, predicts where every landmark
    # lies, so the weak candidates can still confirm it. Detections scoring >= vote_min_score (the detector's
    # own score units) cast the votes; every detection takes part in the verification.
    vote_min_score: float | None = None
    # The verification's inlier tolerance (px + inlier_r x r) and RMS gate, in place of nav.fix's when set: a
    # detector's centre errors grow with the crater (a large rim's shadowed centre is off by 5-10 px on real
    # windows), and without a prior the position comes from the craters alone.
    inlier_r: float | None = None
    max_rms_px: float | None = None
    # How candidates are weighed against each other (module docstring): "inliers" (their count, with
    # ambiguity_margin) or "significance" (-log10 of their chance probability, with ambiguity_log10 and
    # max_log10_nfa). With many candidates verified, a chance transform's best inlier count nears a true one's,
    # so a count margin either refuses true fixes or must stay at few candidates.
    candidate_score: str = "inliers"
    ambiguity_log10: float = 2.0  # significance: a rival elsewhere within this many decades of the best: no fix
    max_log10_nfa: float = -2.0  # significance: the best's false alarms (n_verify x chance) at most 10^this
    # A second detector (a nav/detector option; "": none) whose detections join the verification only, never the
    # vote: detectors miss different craters, and a voted transform needs min_inliers landmarks found by either.
    # Its detections follow the first detector's in the list the fix's inliers index (``voters``).
    verify_detector: str = ""
    # Confirmation by appearance ("": none; "appearance": the craters' candidates are hypotheses, and a window is
    # fixed only where the appearance search, run around one of them, fixes it). A lander carrying the DEM its
    # map was measured in predicts what each landmark looks like: a chance pattern of craters rarely also has
    # the map's terrain where it says. The candidates with >= confirm_min_inliers landmarks, the best supported
    # first and at most confirm_hypotheses of them (one per place, rival_km apart), are searched within
    # confirm_reach_km; two confirmed places: no fix. The search's prior heading is the attitude's, so it needs
    # known_heading.
    confirm: str = ""
    confirm_hypotheses: int = 3
    confirm_min_inliers: int = 3
    confirm_reach_km: float = 4.0
    confirm_min_landmarks: int = 5  # the search's fix needs this many landmarks (nav.fix's min_inliers if more)
    # Places offered by the terrain (:mod:`.terrain_places`): the frame's ground view, or the map window, correlated
    # with the lander's DEM shaded under the frame's Sun over the whole map; its terrain_places best places, on a
    # grid of terrain_pixel_m, are searched before the vote's (confirm_hypotheses of them; 0: the terrain's only).
    # Needs confirm: a place the terrain offers is a hypothesis like the vote's. A place correlating below
    # terrain_min_ncc is not searched (-1: none refused): the search's landmarks are predicted from the same DEM,
    # so a poor correlation confirmed by a few landmarks is not two independent agreements.
    terrain_places: int = 0
    terrain_pixel_m: float = 800.0
    terrain_min_ncc: float = -1.0
    # The frame's own null (significance, known_heading; 0: none): the frame's detections turned about its centre
    # by 90, 180 and 270 degrees (the first null_turns of them) are searched too. At the attitude's heading a
    # turned pattern cannot land on its true place, so the best support a turned copy reaches is chance, measured
    # on this frame's own craters: their number, sizes, clustering and scores, which the chance model's uniform,
    # independent detections do not describe. The best candidate is kept only when its support exceeds every
    # turned copy's by null_margin_log10 decades. Off in every option: three copies are too few draws of chance, so
    # on the south validation windows every margin that fixed more windows than attitude's fixed gate also fixed
    # windows moved so that they cannot be fixed (docs/navigation/fix.md).
    null_turns: int = 0
    null_margin_log10: float = 1.0

    def __post_init__(self):
        for key in ("inlier_r", "max_rms_px"):
            value = getattr(self, key)
            if value is not None and not value > 0:
                raise ValueError(f"{key} must be > 0 (got {value})")
        if self.vote_min_score is not None and not math.isfinite(self.vote_min_score):
            raise ValueError(f"vote_min_score must be a finite number (got {self.vote_min_score})")
        if self.candidate_score not in CANDIDATE_SCORES:
            names = ", ".join(CANDIDATE_SCORES)
            raise ValueError(f"candidate_score must be one of {names} (got {self.candidate_score!r})")
        for key in ("ambiguity_log10", "max_log10_nfa"):
            if not math.isfinite(getattr(self, key)):
                raise ValueError(f"{key} must be a finite number (got {getattr(self, key)})")
        if self.heading_tol_deg is not None and not 0 < self.heading_tol_deg <= self.bin_deg:
            raise ValueError(f"heading_tol_deg must be in (0, bin_deg = {self.bin_deg}] (got {self.heading_tol_deg})")
        if self.confirm not in CONFIRMS:
            raise ValueError(f"confirm must be one of {', '.join(map(repr, CONFIRMS))} (got {self.confirm!r})")
        if self.confirm and not self.known_heading:
            raise ValueError("confirm needs known_heading: the search predicts the frame at the attitude's heading")
        counts = (self.confirm_hypotheses + self.terrain_places, self.confirm_min_inliers, self.confirm_min_landmarks)
        if min(counts) < 1 or min(self.confirm_hypotheses, self.terrain_places) < 0 or not self.confirm_reach_km > 0:
            raise ValueError(
                "confirm_hypotheses and terrain_places must be >= 0 with one >= 1, confirm_min_inliers and "
                "confirm_min_landmarks >= 1 and confirm_reach_km > 0 (got "
                f"{self.confirm_hypotheses}, {self.terrain_places}, {counts[1]}, {counts[2]}, {self.confirm_reach_km})"
            )
        if self.terrain_places and not self.confirm:
            raise ValueError("terrain_places needs confirm: a place the terrain offers is a hypothesis to confirm")
        if not self.terrain_pixel_m > 0:
            raise ValueError(f"terrain_pixel_m must be > 0 (got {self.terrain_pixel_m})")
        if not -1.0 <= self.terrain_min_ncc < 1.0:
            raise ValueError(f"terrain_min_ncc must be in [-1, 1) (got {self.terrain_min_ncc})")
        if self.ambiguity_log10 < 0:
            raise ValueError(f"ambiguity_log10 must be >= 0 (got {self.ambiguity_log10})")
        if self.null_turns not in (0, 1, 2, 3):
            raise ValueError(f"null_turns must be 0, 1, 2 or 3 quarter turns (got {self.null_turns})")
        if self.null_turns and not (self.known_heading and self.candidate_score == "significance"):
            raise ValueError(
                "null_turns needs known_heading (heading free, a turned frame lands on its true place) and "
                "candidate_score=significance (the margin is in decades of chance)"
            )
        if not (math.isfinite(self.null_margin_log10) and self.null_margin_log10 >= 0):
            raise ValueError(f"null_margin_log10 must be a finite number >= 0 (got {self.null_margin_log10})")

    def as_dict(self) -> dict:
        return asdict(self)

    def verify_params(self, fparams: FixParams, heading_known: bool = False) -> FixParams:
        """``fparams`` as the verification of a voted candidate uses them: this group's inlier count and
        tolerances, the heading free within a vote cell (``heading_known``: within ``heading_tol_deg``, when
        set, of the attitude's)."""
        turn = self.heading_tol_deg if heading_known and self.heading_tol_deg is not None else self.bin_deg
        changes = {"min_inliers": self.min_inliers, "max_heading_deg": turn}
        if self.inlier_r is not None:
            changes["inlier_r"] = self.inlier_r
        if self.max_rms_px is not None:
            changes["max_rms_px"] = self.max_rms_px
        return replace(fparams, **changes)

    def confirm_params(self, fparams: FixParams) -> FixParams:
        """``fparams`` as a confirmation's search fixes one place: within ``confirm_reach_km`` of it, with at least
        ``confirm_min_landmarks`` landmarks (``fparams``' own minimum if more)."""
        need = max(fparams.min_inliers, self.confirm_min_landmarks)
        return replace(fparams, prior_sigma_km=self.confirm_reach_km, min_inliers=need)

    def no_place_reason(self) -> str:
        """Why a confirmation had no place to search (:func:`confirm_places` empty)."""
        vote = f"no candidate with {self.confirm_min_inliers} landmarks" if self.confirm_hypotheses else ""
        terrain = f"no terrain place correlating >= {self.terrain_min_ncc:.2f}" if self.terrain_places else ""
        return "no place to confirm: " + ", ".join(x for x in (terrain, vote) if x)


def window_heading_deg(params: LostInSpaceParams) -> float | None:
    """A map window's heading for the vote: 0 (north-up) when the attitude gives it, else None (free)."""
    return 0.0 if params.known_heading else None


@dataclass(frozen=True)
class PairIndex:
    """Ordered landmark pairs of a map, sorted by map distance (m)."""

    lm_xy: np.ndarray  # (n, 2) map metres of every landmark of the map
    lm_r_m: np.ndarray  # (n,) radii, m
    i: np.ndarray  # (k,) first landmark of each ordered pair
    j: np.ndarray
    dist_m: np.ndarray  # (k,) sorted ascending


def build_index(landmarks, params: LostInSpaceParams = LostInSpaceParams()) -> PairIndex:
    """Every ordered pair of landmarks >= ``min_landmark_km`` closer than ``max_pair_km``, sorted by distance."""
    xy = np.array([[lm.x_m, lm.y_m] for lm in landmarks], float).reshape(-1, 2)
    r = np.array([lm.diameter_km for lm in landmarks], float) * 500.0
    big = np.nonzero(r >= params.min_landmark_km * 500.0)[0]
    d = np.hypot(*(xy[big][:, None, :] - xy[big][None, :, :]).transpose(2, 0, 1))
    a, b = np.nonzero((d <= params.max_pair_km * 1000.0) & (d > 0))
    order = np.argsort(d[a, b], kind="stable")
    return PairIndex(xy, r, big[a[order]], big[b[order]], d[a, b][order])


def _votes(det_z, det_r, index: PairIndex, pixel_m: float, p: LostInSpaceParams):
    """Pair matches: (frame det i, det j, landmark a, landmark b, complex a) for every frame pair whose
    distance and diameters agree with a map pair; ``det_z`` pixel points as complex (u - i v)."""
    n = det_z.size
    ii, jj = np.triu_indices(n, 1)
    ii, jj = np.concatenate([ii, jj]), np.concatenate([jj, ii])  # both orders: the map index is ordered too
    dpx = np.abs(det_z[jj] - det_z[ii])
    tol = (p.dist_tol_px + p.dist_tol_r * (det_r[ii] + det_r[jj])) * pixel_m
    lo = np.searchsorted(index.dist_m, dpx * pixel_m - tol, "left")
    hi = np.searchsorted(index.dist_m, dpx * pixel_m + tol, "right")
    cnt = hi - lo
    if cnt.sum() == 0:
        return None
    q = np.repeat(np.arange(ii.size), cnt)
    k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)
    la, lb = index.i[k], index.j[k]
    ra = det_r[ii[q]] * pixel_m / index.lm_r_m[la]
    rb = det_r[jj[q]] * pixel_m / index.lm_r_m[lb]
    ok = _within_ratio(ra, p.radius_ratio) & _within_ratio(rb, p.radius_ratio)
    q, la, lb = q[ok], la[ok], lb[ok]
    if q.size > p.max_matches:  # bounded work: keep the matches of smallest relative distance error
        err = np.abs(index.dist_m[k[ok]] - dpx[q] * pixel_m) / tol[q]
        keep = np.argsort(err, kind="stable")[: p.max_matches]
        q, la, lb = q[keep], la[keep], lb[keep]
    wa = index.lm_xy[la, 0] + 1j * index.lm_xy[la, 1]
    wb = index.lm_xy[lb, 0] + 1j * index.lm_xy[lb, 1]
    a = (wb - wa) / (det_z[jj[q]] - det_z[ii[q]])
    return ii[q], jj[q], la, lb, a, wa - a * det_z[ii[q]]


def _within_ratio(ratio, limit: float):
    """Radius ratios within [1/``limit``, ``limit``]: a detection and a landmark of compatible size."""
    return (ratio <= limit) & (ratio >= 1.0 / limit)


def _predicted_landmarks(index: PairIndex, a: complex, b: complex, p) -> tuple[np.ndarray, np.ndarray]:
    """(indices of the landmarks >= ``min_landmark_km``, their points under the inverse of the transform
    pixel -> map (a, b), as complex u - i v)."""
    lm = np.nonzero(index.lm_r_m >= p.min_landmark_km * 500.0)[0]
    return lm, (index.lm_xy[lm, 0] + 1j * index.lm_xy[lm, 1] - b) / a


def _candidate_pairs(det_z, det_r, index: PairIndex, a: complex, b: complex, pixel_m: float, p, fparams):
    """(detection, landmark) pairs of the landmarks a candidate transform predicts in the frame."""
    lm, z = _predicted_landmarks(index, a, b, p)
    r_lm = index.lm_r_m[lm] / pixel_m
    gate = p.gate_km * 1000.0 / pixel_m
    d = np.abs(det_z[:, None] - z[None, :])
    ok = (d <= gate + 0.25 * r_lm[None, :]) & _within_ratio(det_r[:, None] / r_lm[None, :], fparams.radius_ratio)
    di, lj = np.nonzero(ok)
    return np.stack([di, lm[lj]], axis=1)


_FLIP_V = np.array([1.0, -1.0])  # (u, v) -> (u, -v): pixel -> map is then a proper similarity


def _pair_vote_cells(va: np.ndarray, centre: np.ndarray, params: LostInSpaceParams):
    """Accumulate the votes (frame-centre position ``centre`` and heading angle(``va``)) in cells of
    ``bin_km`` x ``bin_km`` x ``bin_deg``: (vote of each cell entry, cell of each entry, the ``n_verify``
    fullest cells)."""
    head = np.angle(va)
    # Each vote goes to the 2 x 2 x 2 block of cells around it (a grid offset by half a cell), so a
    # solution lying on a cell edge is not split; the heading wraps around.
    n_head = max(1, round(360.0 / params.bin_deg))
    f = np.stack(
        [
            centre.real / (params.bin_km * 1000.0),
            centre.imag / (params.bin_km * 1000.0),
            np.degrees(head) % 360.0 / (360.0 / n_head),
        ],
        axis=1,
    )
    base = np.floor(f - 0.5).astype(np.int64)
    offs = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int64)
    cell = (base[:, None, :] + offs[None, :, :]).reshape(-1, 3)
    cell[:, 2] %= n_head
    vote_of = np.repeat(np.arange(len(centre)), len(offs))
    # One int64 key per cell (x, y offsets of 2^20 cells cover any map): np.unique on a 1-D array is fast.
    key = ((cell[:, 0] + (1 << 20)) << 22 | (cell[:, 1] + (1 << 20))) * (n_head + 1) + cell[:, 2]
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    return vote_of, inv, np.argsort(-counts, kind="stable")[: params.n_verify]


class Candidate(NamedTuple):
    """A verified vote cell: its support (module docstring, "Candidate score"), its RANSAC fix (None: no
    transform), its transform pixel -> map (a, b), the map point under the frame centre, and its inlier count."""

    support: float
    fix: Fix | None
    a: complex
    b: complex
    centre: complex
    inliers: int


def chance_log10(k: int, expected: float) -> float:
    """log10 of P(X >= ``k``) for X Poisson with mean ``expected``: the chance that ``k`` or more inliers come
    from detections placed at random. Summed upwards from the k-th term in log space, exact where 1 - cdf
    would round to 0."""
    if k <= 0:
        return 0.0
    if expected <= 0.0:
        return -math.inf
    i = np.arange(k, k + 60 + int(4.0 * expected))
    log_terms = -expected + i * math.log(expected) - np.array([math.lgamma(n + 1.0) for n in i])
    top = float(log_terms.max())
    return (top + math.log(float(np.exp(log_terms - top).sum()))) / math.log(10.0)


def chance_inliers(det_r, index: PairIndex, a: complex, b: complex, frame_shape, pixel_m, params, vparams) -> float:
    """Expected number of the landmarks a transform (a, b) predicts in the frame that detections of compatible
    radius, placed at random, match within the verification's inlier tolerance (module docstring; the
    tolerance taken at the landmark's radius)."""
    h, w = frame_shape
    lm, z = _predicted_landmarks(index, a, b, params)
    inside = (z.real >= 0) & (z.real < w) & (-z.imag >= 0) & (-z.imag < h)
    r_lm = index.lm_r_m[lm[inside]] / pixel_m
    n_compatible = _within_ratio(np.asarray(det_r, float)[None, :] / r_lm[:, None], vparams.radius_ratio).sum(axis=1)
    disc = math.pi * (vparams.inlier_px + vparams.inlier_r * r_lm) ** 2
    return float(np.sum(1.0 - np.exp(-n_compatible * disc / float(h * w))))


def _verified_candidates(
    cells, va, centre, zc, det_uv, det_z, det_r, index, pixel_m, params, fparams, frame_shape, heading_deg=None
) -> list[Candidate]:
    """Verify each vote cell's candidate transform by RANSAC against the map, and score it
    (``params.candidate_score``). ``heading_deg``: the attitude's heading (:func:`lost_in_space_fix`)."""
    vote_of, inv, best_cells = cells
    flip = _FLIP_V
    # The candidate's heading is known to about a vote cell: RANSAC may turn it by up to that much; with the
    # attitude's heading and heading_tol_deg, it starts from that heading and turns by up to the tolerance.
    attitude = heading_deg is not None and params.heading_tol_deg is not None
    vparams = params.verify_params(fparams, heading_known=attitude)
    cands = []
    for c in best_cells:
        sel = vote_of[inv == c]
        # Candidate transform: mean heading (unit phasors; the attitude's when it is held to it) at the known
        # scale, mean centre.
        ph = np.exp(1j * math.radians(heading_deg)) if attitude else np.mean(va[sel] / np.abs(va[sel]))
        a0 = complex(pixel_m * ph / abs(ph))
        c0 = complex(np.median(centre[sel].real), np.median(centre[sel].imag))
        b0 = c0 - a0 * zc
        pairs = _candidate_pairs(det_z, det_r, index, a0, b0, pixel_m, params, fparams)
        fix, a, b = ransac_similarity(det_uv * flip, det_r, index.lm_xy, pairs, a0, vparams)
        if a == 0j:
            cands.append(Candidate(0.0, None, a0, b0, c0, 0))
            continue
        n = len(fix.inliers) if fix.ok else len(inliers_of(a, b, det_uv * flip, det_r, index.lm_xy, pairs, vparams))
        support = float(n)
        if params.candidate_score == "significance" and n:  # no inlier (a degenerate transform too): no evidence
            expected = chance_inliers(det_r, index, a, b, frame_shape, pixel_m, params, vparams)
            support = -chance_log10(n, expected)
        cands.append(Candidate(support, fix, a, b, complex(a * zc + b), n))
    return cands


def unambiguous_candidate(cands: list[Candidate], params: LostInSpaceParams):
    """(the best verified candidate, None), or (None, the "no fix" saying why: none verified, the best not
    significant, or a rival candidate far away with about as much support)."""
    oks = [c for c in cands if c.fix is not None and c.fix.ok]
    if not oks:
        best = max(cands, key=lambda c: c.support)
        reason = best.fix.reason if best.fix is not None else "no candidate pairs with the map's landmarks"
        return None, Fix(False, f"no candidate verified (best: {reason})")
    best = max(oks, key=lambda c: (c.support, -c.fix.rms_px))
    significance = params.candidate_score == "significance"
    if significance and math.log10(len(cands)) - best.support > params.max_log10_nfa:
        return None, Fix(
            False,
            f"not significant: {best.inliers} landmarks agree, chance 1e{-best.support:.1f} "
            f"over {len(cands)} candidates (at most 1e{params.max_log10_nfa:g} allowed)",
        )
    margin = params.ambiguity_log10 if significance else params.ambiguity_margin
    for rival in cands:
        if rival is best or abs(rival.centre - best.centre) <= params.rival_km * 1000.0:
            continue
        if rival.support >= best.support - margin and rival.inliers >= 3:
            return None, Fix(
                False,
                f"ambiguous: candidates {abs(rival.centre - best.centre) / 1000.0:.0f} km apart agree "
                f"({best.inliers} and {rival.inliers} landmarks)",
            )
    return best, None


def _fix_from_inliers(fix: Fix, det_uv: np.ndarray, index: PairIndex, frame_shape) -> Fix:
    """``fix`` with the similarity refitted on its inliers: the map point under the frame centre, the
    scale and the heading (or "no fix" for a degenerate inlier set)."""
    h, w = frame_shape
    flip = _FLIP_V
    idx = np.array(fix.inliers)
    a, b = fit_similarity((det_uv * flip)[idx[:, 0]], index.lm_xy[idx[:, 1]])
    c = apply_similarity(a, b, np.array([[w / 2.0, -h / 2.0]]))[0]
    if not np.all(np.isfinite(c)):
        return Fix(False, "degenerate inlier set (coincident detections)")
    fix.x_m, fix.y_m = float(c[0]), float(c[1])
    fix.scale_m_per_px = float(abs(a))
    fix.heading_deg = float(math.degrees(np.angle(a)))
    return fix


def lost_in_space_fix(*args, **kwargs) -> Fix:
    """The fix of :func:`lost_in_space_search` (same arguments), without its candidates."""
    return lost_in_space_search(*args, **kwargs)[0]


def hypotheses(cands: list[Candidate], params: LostInSpaceParams) -> list[Candidate]:
    """The places a confirmation searches (``params.confirm``): the candidates agreeing with at least
    ``confirm_min_inliers`` landmarks, best supported first (then fewest RMS), one per place (a candidate
    within ``rival_km`` of a better one is the same place), at most ``confirm_hypotheses``."""
    ranked = sorted(
        (c for c in cands if c.inliers >= params.confirm_min_inliers),
        key=lambda c: (-c.support, c.fix.rms_px if c.fix is not None and c.fix.ok else math.inf),
    )
    kept: list[Candidate] = []
    if params.confirm_hypotheses == 0:
        return kept
    for c in ranked:
        if all(abs(c.centre - k.centre) > params.rival_km * 1000.0 for k in kept):
            kept.append(c)
        if len(kept) == params.confirm_hypotheses:
            break
    return kept


def confirm_places(terrain: list[tuple[complex, float]], cands: list[Candidate], params: LostInSpaceParams):
    """(source, map point, support) of every place a confirmation searches, in order: the ``terrain``'s places
    ((point, correlation), best first) correlating at least ``terrain_min_ncc``, then the vote's :func:`hypotheses`
    more than ``rival_km`` from all of them."""
    places = [("terrain", centre, float(ncc)) for centre, ncc in terrain if ncc >= params.terrain_min_ncc]
    for cand in hypotheses(cands, params):
        if all(abs(cand.centre - p[1]) > params.rival_km * 1000.0 for p in places):
            places.append(("vote", cand.centre, cand.support))
    return places


# A place elsewhere (:func:`places_elsewhere`) lies beyond a 512 px window's diagonal at 400 m/px from the frame.
PLACE_MIN_KM, PLACE_JITTER_KM = 300.0, 10.0


def places_elsewhere(key: str, centre_xy, landmarks, n: int, min_landmark_km: float) -> list[complex]:
    """``n`` map points (x + iy), seeded by ``key``, where a frame whose true place is ``centre_xy`` is not, to test
    a confirmation against chance: landmarks >= ``min_landmark_km`` at least :data:`PLACE_MIN_KM` from that place
    (a vote's places lie on crater patterns), each moved by up to :data:`PLACE_JITTER_KM`."""
    rng = np.random.default_rng(zlib.crc32(key.encode()))
    cx, cy = centre_xy
    far = [lm for lm in landmarks if lm.diameter_km >= min_landmark_km]
    far = [lm for lm in far if math.hypot(lm.x_m - cx, lm.y_m - cy) >= PLACE_MIN_KM * 1000.0]
    picks = rng.choice(len(far), size=min(n, len(far)), replace=False)
    jitter = rng.uniform(-PLACE_JITTER_KM, PLACE_JITTER_KM, size=(len(picks), 2)) * 1000.0
    return [complex(far[i].x_m + dx, far[i].y_m + dy) for i, (dx, dy) in zip(picks, jitter)]


def moved_detections(det_uv, det_r, m: np.ndarray, frame_shape):
    """(points, radii, kept): detections at ``det_uv`` (u right, v down) of radii ``det_r`` moved by the affine map
    ``m`` (2 x 3: (u, v) -> m[:, :2] (u, v) + m[:, 2]; a radius scales by sqrt |det m[:, :2]|); ``kept`` marks the
    centres that stay inside a frame of ``frame_shape``."""
    uv = np.asarray(det_uv, float).reshape(-1, 2) @ m[:, :2].T + m[:, 2]
    r = np.asarray(det_r, float) * math.sqrt(abs(np.linalg.det(m[:, :2])))
    h, w = frame_shape
    kept = (uv[:, 0] >= 0.0) & (uv[:, 0] < w) & (uv[:, 1] >= 0.0) & (uv[:, 1] < h)
    return uv, r, kept


def quarter_turn(frame_shape, k: int) -> np.ndarray:
    """The affine map (:func:`moved_detections`) turning a frame's pixels by ``k`` x 90 degrees about its centre."""
    h, w = frame_shape
    c, s = round(math.cos(k * math.pi / 2.0)), round(math.sin(k * math.pi / 2.0))
    rot = np.array([[c, -s], [s, c]], float)
    centre = np.array([w / 2.0, h / 2.0])
    return np.concatenate([rot, (centre - rot @ centre)[:, None]], axis=1)


def _search(det_uv, det_r, voters, index: PairIndex, frame_shape, pixel_m, params, fparams, heading_deg):
    """(every verified candidate, None) of the detections (arrays) whose indices ``voters`` cast the votes, or ([], the
    "no fix" saying why the vote could not run)."""
    det_z = det_uv[:, 0] - 1j * det_uv[:, 1]  # (u, -v): pixel -> map is then a proper similarity
    top = voters[np.argsort(-det_r[voters], kind="stable")[: params.n_detections]]
    votes = _votes(det_z[top], det_r[top], index, pixel_m, params)
    if votes is None or votes[0].size == 0:
        return [], Fix(False, "no crater pair of the frame matches a pair of the map")
    _, _, _, _, va, vb = votes
    if heading_deg is not None:  # the attitude fixes the heading: a vote turned away from it is a chance match
        near = np.abs(np.angle(va * np.exp(-1j * math.radians(heading_deg)), deg=True)) <= params.bin_deg
        va, vb = va[near], vb[near]
        if va.size == 0:
            return [], Fix(False, "no crater pair of the frame matches a pair of the map at the known heading")
    h, w = frame_shape
    zc = w / 2.0 - 1j * h / 2.0
    centre = va * zc + vb
    cells = _pair_vote_cells(va, centre, params)
    cands = _verified_candidates(
        cells, va, centre, zc, det_uv, det_z, det_r, index, pixel_m, params, fparams, frame_shape, heading_deg
    )
    return cands, None


def own_null_support(det_uv, det_r, voters, index, frame_shape, pixel_m, params, fparams, heading_deg) -> float:
    """The best support (-log10 chance) that the frame's detections, turned by 90, 180 and 270 degrees about its centre
    (the first ``params.null_turns``), reach at the attitude's heading ``heading_deg``: chance measured on this frame's
    own craters (``LostInSpaceParams.null_turns``). 0 where no turned copy verifies a candidate transform."""
    best = 0.0
    for k in range(1, params.null_turns + 1):
        uv, r, kept = moved_detections(det_uv, det_r, quarter_turn(frame_shape, k), frame_shape)
        renumbered = np.cumsum(kept) - 1  # a kept detection's index among the kept
        turned_voters = renumbered[voters[kept[voters]]]
        if turned_voters.size < 3:
            continue
        cands, _ = _search(uv[kept], r[kept], turned_voters, index, frame_shape, pixel_m, params, fparams, heading_deg)
        best = max([best, *(c.support for c in cands if c.fix is not None)])
    return best


def lost_in_space_search(
    detections,
    landmarks,
    frame_shape,
    pixel_m: float,
    params: LostInSpaceParams = LostInSpaceParams(),
    fparams: FixParams = FixParams(),
    index: PairIndex | None = None,
    heading_deg: float | None = None,
    voters: int | None = None,
) -> tuple[Fix, list[Candidate]]:
    """(the fix, every verified candidate) of a nadir frame of known pixel size ``pixel_m`` (map metres) with no
    position or heading prior. The fix: the map point under the frame centre, or "no fix" (module docstring).
    The candidates are what a confirmation (:func:`hypotheses`) searches; none when the vote could not run.
    ``index``: a prebuilt :func:`build_index` of ``landmarks`` (built here when None). ``heading_deg``: the
    frame's heading on the map when an attitude gives it (the angle of the pixel -> map similarity); only votes
    within one heading cell (``bin_deg``) of it count. ``voters``: only the first ``voters`` detections may vote
    (the rest, a ``verify_detector``'s, take part in the verification only); None: all."""
    index = index if index is not None else build_index(landmarks, params)
    if len(detections) < max(3, params.min_inliers):
        return Fix(False, f"{len(detections)} detections (need {max(3, params.min_inliers)})"), []
    det_uv = np.array([[d.u, d.v] for d in detections], float)
    det_r = np.array([d.r for d in detections], float)
    voters = np.arange(len(detections) if voters is None else min(voters, len(detections)))
    if params.vote_min_score is not None:
        voters = voters[np.array([detections[i].score for i in voters], float) >= params.vote_min_score]
        if voters.size < 3:
            return Fix(False, f"{voters.size} detections score >= {params.vote_min_score} (need 3 to vote)"), []
    search = (index, frame_shape, pixel_m, params, fparams, heading_deg)
    cands, no_vote = _search(det_uv, det_r, voters, *search)
    if no_vote is not None:
        return no_vote, []
    best, no_fix = unambiguous_candidate(cands, params)
    null = math.nan
    if best is not None and params.null_turns:  # measured only where a fix would be made: it costs a search a turn
        null = own_null_support(det_uv, det_r, voters, *search)
        if best.support < null + params.null_margin_log10:
            no_fix = Fix(
                False,
                f"within chance of its own turned craters: chance 1e{-best.support:.1f}, turned 1e{-null:.1f} "
                f"(a margin of {params.null_margin_log10:g} decades needed)",
            )
            best = None
    if best is None:
        no_fix.support = max((c.support for c in cands if c.fix is not None and c.fix.ok), default=math.nan)
        no_fix.null_support = null
        return no_fix, cands
    fix = _fix_from_inliers(best.fix, det_uv, index, frame_shape)
    fix.support, fix.null_support = best.support, null
    return fix, cands
