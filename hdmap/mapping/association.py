"""Ray-to-landmark association: gating, per-image assignment, per-pass offset.

All geometry is in one local metric frame (ENU of the tile being processed).

Gating statistic of ray j (origin a, measured azimuth/elevation) against a
landmark at x with covariance C: with v = x - a, the predicted angles
``az(v), el(v)`` and their Jacobian J (2x3),

    chi2 = r^T S^-1 r,  r = (wrap(az(v) - az_j), el(v) - el_j),
    S = diag(s_az^2, s_el^2) + J (C + Sigma_a) J^T,

where Sigma_a is the origin's position covariance. Under the ray's noise model
chi2 ~ chi-square with 2 degrees of freedom.

One pass shares its GNSS bias (metres, unknown to the vehicle). Before anything
is known, that bias is part of Sigma_a (``pass_bias_sigma_m``), which makes the
gate wide. Rays of one unit (one vehicle pass, one tile, one upload) that gate
to landmarks then estimate the pass's offset delta by weighted least squares on
their perpendicular residuals,

    (sum_j w_j P_j + I / s_b^2) delta = sum_j w_j P_j (x_L(j) - a_j),

and the gate is re-run with origins a_j + delta and Sigma_a = white + Cov(delta).
That is what keeps two same-class signs a few metres apart apart: the offset is
shared by all rays of the pass, so one sign the pass sees well fixes it for all.

Detections of one image never share a landmark: each image's assignment is a
small linear assignment problem (:func:`hdmap.mapping.assignment.min_cost_assignment`) on chi2.

Pitfall (signs on one line of sight, open): two same-class signs one behind the other
(the fleet evaluation's seed 0 signs 99 and 167, 10.6 m apart and 1.3 degrees apart from
the street that sees both at 42-59 m; 167 the nearer and seen only from there, 99 also
head-on from a second street at 6-25 m). 167's landmark starts at 167 and ends between
the two, confirmed, holding 99's rays, most of them brought by young landmarks merged into
it: a quarter of the passes link none of 99's near rays, which start young landmarks with
the pass's far rays of both signs (association gives them to 99's landmark in nearly all of
those passes; the group check takes them back, see ``MatchingConfig.group_check``). From
the first street the rays and box ranges (about 20 % sigma) fit either landmark, per ray
and per track alike. Nothing here weighs "a new sign behind" against a link; a test on one
track, the track's own triangulation against "an unmapped sign here", did not separate
right links from wrong ones; ``offset_hypothesis_margin`` 0 (the best-scored fit wins)
removes the false landmark on the simulated receiver's logs but adds false landmarks on
the phones' (docs/experiments/2026-12-line-of-sight-mixture.md,
2026-12-group-check-tracks.md, 2026-12-group-check-by-track.md).

>>> import numpy as np
>>> angles(np.array([[1.0, 1.0, 0.0]]))[0].round(4).tolist()
[0.7854]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.signs import DEFAULT_SIZE_REL_SIGMA
from hdmap.mapping.assignment import min_cost_assignment
from hdmap.mapping.box_ranges import REL_FLOOR
from hdmap.mapping.estimator.gating import wrap
from hdmap.mapping.estimator.model import ray_angles as angles
from hdmap.mapping.estimator.terms import white_rel_var
from hdmap.mapping.facing import FacingConfig

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_BIG = 1e12


@dataclass(frozen=True)
class GateConfig:
    chi2_gate: float = 13.82
    """Gate on the 2-dof statistic (13.82 = 99.9%)."""
    pass_bias_sigma_m: float = 3.0
    """Assumed per-axis std of a pass's unknown GNSS bias before the offset is estimated."""
    vertical_bias_sigma_m: float = 3.0
    angle_floor_rad: float = 0.003
    """Added in quadrature to reported angular sigmas (unmodelled calibration, timing)."""
    min_range_m: float = 2.0
    max_range_m: float = 120.0
    range_k: float = 3.0
    """A range estimate must agree with the landmark distance within range_k sigma."""
    range_in_cost: bool = True
    """Add the range residual (from the box size) to the statistic of ranged rays: same-class
    signs a few metres apart along a road are seen along nearly the same bearing, their
    ranges differ."""
    landmark_scale: Literal["off", "cost", "both"] = "both"
    """How a candidate's own panel scale (``Landmark.scale``) enters the range test: its
    box ranges then predict the distance with only the box's white noise, not the
    catalogue's panel spread every ray of one panel shares. "off": not used; "cost": in
    the statistic only (the range gate keeps the catalogue's spread); "both": in the
    gate too."""
    scale_min_passes: int = 5
    """Passes a landmark needs before its panel scale is used."""
    scale_rel_sigma: float = 0.03
    """Relative sigma added to a scaled range prediction (the scale's own error and
    vehicles' camera calibrations)."""
    offset_iterations: int = 2
    min_offset_rays: int = 3
    """Rays needed before a unit's offset is estimated (fewer: the wide gate stays)."""
    track_link_factor: float = 1.0
    """A tracked ray links to its track's landmark when its statistic is within this
    multiple of ``chi2_gate`` (the track, not the ray alone, chose the landmark)."""
    offset_hypotheses: int = 3
    """A unit with tracks also tries the offsets that put its longest track on each of its
    candidate landmarks (at most this many, most gated rays first), each iterated like the
    first; 0 = only the offset from the wide-gate assignment. Against a lattice of
    identical signs (a row of parking signs 8.5 m apart) the wide gate can settle on the
    neighbouring alignment, which the offset then follows."""
    offset_hypothesis_margin: float = 13.82
    """An alternative replaces the fit it is compared with only when its score (the linked
    pairs' summed margins ``chi2_gate - chi2`` minus the offset's prior chi-square) is
    higher by this much (one ``chi2_gate``: about one more well-fitting ray)."""
    facing: FacingConfig = field(default_factory=FacingConfig)
    """The facing gate (:mod:`hdmap.mapping.facing`): a ray seen from beyond a landmark's
    visibility cone is not a candidate of it (applies only when :func:`associate` is given
    the candidates' facings)."""


@dataclass(frozen=True)
class LocalRays:
    """Rays of one unit in a local metric frame (struct of arrays)."""

    origin: Array
    direction: Array
    sigma_az: Array
    sigma_el: Array
    sigma_pos_h: Array
    sigma_pos_v: Array
    range_m: Array
    sigma_range_m: Array
    image: IntArray
    sign_class: IntArray
    track: IntArray | None = None
    """Per ray its track within the unit (detections of one sign followed from image to
    image by the vehicle); 0 = not tracked. None = no ray tracked."""

    def __len__(self) -> int:
        return int(self.origin.shape[0])

    def take(self, idx: NDArray) -> LocalRays:
        return LocalRays(
            **{
                k: None if getattr(self, k) is None else getattr(self, k)[idx]
                for k in self.__dataclass_fields__
            }
        )

    @staticmethod
    def concat(parts: list[LocalRays]) -> LocalRays:
        """Rows of ``parts`` in order (tracks kept only when every part has them)."""
        return LocalRays(
            **{
                k: None
                if any(getattr(p, k) is None for p in parts)
                else np.concatenate([getattr(p, k) for p in parts])
                for k in LocalRays.__dataclass_fields__
            }
        )

    @property
    def tracks(self) -> IntArray:
        """``track``, zeros when None."""
        return np.zeros(len(self), np.int64) if self.track is None else self.track


def origin_cov(rays: LocalRays, bias_h: float, bias_v: float) -> Array:
    """(n, 3, 3) position covariance of the origins, with an assumed shared bias."""
    n = len(rays)
    c = np.zeros((n, 3, 3))
    c[:, 0, 0] = c[:, 1, 1] = rays.sigma_pos_h**2 + bias_h**2
    c[:, 2, 2] = rays.sigma_pos_v**2 + bias_v**2
    return c


def pair_chi2(
    rays: LocalRays,
    ri: IntArray,
    x: Array,
    cov: Array,
    a_cov: Array,
    cfg: GateConfig,
    offset: Array | None = None,
) -> tuple[Array, NDArray[np.bool_]]:
    """Gating statistic for pairs (ray ri[k], landmark k of x/cov) and the plausibility mask
    (in front of the camera, within the gate's ranges, the box range consistent); the
    statistic is ``inf`` where the pair is not plausible.

    ``a_cov`` is the (len(rays), 3, 3) origin covariance; ``offset`` shifts origins.

    The cheap tests come first and the statistic is evaluated on the pairs that pass them
    only (about a quarter of a unit's same-class pairs in the fleet evaluation): row by row
    the same arithmetic as over all pairs, so the values are the same to the bit.
    """
    return pair_stat(rays, Pairs.of(rays, ri, x, cov), a_cov, cfg, offset)


@dataclass(frozen=True)
class Pairs:
    """A unit's (ray, landmark) pairs with what the statistic needs gathered once: the
    unit's offset hypotheses evaluate the same pairs again and again."""

    ri: IntArray
    origin: Array
    direction: Array
    x: Array
    cov: Array
    measured: Array
    """(k, 2) the rays' measured azimuth and elevation."""
    scale: Array | None = None
    """(k,) the landmark's panel scale per pair (NaN: unknown), or None."""
    panel_rel_sigma: float = DEFAULT_SIZE_REL_SIGMA
    """The catalogue's panel spread in the rays' range sigmas, taken out with ``scale``."""

    @staticmethod
    def of(rays: LocalRays, ri: IntArray, x: Array, cov: Array) -> Pairs:
        """Pairs of rays ``ri`` with landmarks at ``x`` (one per pair) and covariances."""
        az, el = angles(rays.direction)
        return Pairs(
            ri, rays.origin[ri], rays.direction[ri], x, cov, np.stack([az, el], axis=-1)[ri]
        )


def pair_stat(
    rays: LocalRays,
    p: Pairs,
    a_cov: Array,
    cfg: GateConfig,
    offset: Array | None,
    rows: IntArray | None = None,
) -> tuple[Array, NDArray[np.bool_]]:
    """:func:`pair_chi2` of pre-gathered pairs; with ``rows``, of those pairs only (the
    others: ``inf``, not plausible; ``offset``, if an array, one row per pair of ``rows``)."""
    src = slice(None) if rows is None else rows
    ri, x = p.ri[src], p.x[src]
    a = p.origin[src] + (0.0 if offset is None else offset)
    d = p.direction[src]
    v = x - a
    rng = np.linalg.norm(v, axis=-1)
    front = np.einsum("kj,kj->k", v, d) > 0
    ok = front & (rng >= cfg.min_range_m) & (rng <= cfg.max_range_m)
    chi2 = np.full(ri.size, np.inf)
    k = np.flatnonzero(ok)
    if k.size:
        kp = k if rows is None else rows[k]  # into p's rows
        rk, vk, dk, rng_k = ri[k], v[k], d[k], rng[k]
        c = p.cov[kp] + a_cov[rk]
        # the symmetric C's six terms: the products below are written out (numpy's
        # batched matmul and einsum over 2x3 and 3x3 blocks cost far more per pair)
        c00, c01, c02 = c[:, 0, 0], c[:, 0, 1], c[:, 0, 2]
        c11, c12, c22 = c[:, 1, 1], c[:, 1, 2], c[:, 2, 2]
        r_est = rays.range_m[rk]
        has_r = r_est > 0
        # landmark distance uncertainty along the ray: origin and landmark position spread
        d0, d1, d2 = dk[:, 0], dk[:, 1], dk[:, 2]
        along = np.sqrt(
            d0 * d0 * c00
            + d1 * d1 * c11
            + d2 * d2 * c22
            + 2.0 * (d0 * d1 * c01 + d0 * d2 * c02 + d1 * d2 * c12)
        )
        s_r = np.hypot(rays.sigma_range_m[rk], along)
        r_cost, s_cost = r_est, s_r
        if p.scale is not None and cfg.landmark_scale != "off":
            sc = p.scale[kp]
            known = has_r & np.isfinite(sc) & (sc > 0)
            _, _, rel_w2 = white_rel_var(
                r_est, rays.sigma_range_m[rk], p.panel_rel_sigma, REL_FLOOR
            )
            r_cost = np.where(known, r_est * np.where(known, sc, 1.0), r_est)
            s_sharp = np.sqrt(r_cost**2 * (rel_w2 + cfg.scale_rel_sigma**2) + along**2)
            s_cost = np.where(known, s_sharp, s_r)
            if cfg.landmark_scale == "both":
                r_est, s_r = r_cost, s_cost
        good = ~has_r | (np.abs(rng_k - r_est) <= cfg.range_k * s_r)
        ok[k[~good]] = False
        k, kp, rk, vk = k[good], kp[good], rk[good], vk[good]
        c00, c01, c02, c11, c12, c22 = (t[good] for t in (c00, c01, c02, c11, c12, c22))
        rng_k, r_est, has_r, s_r = rng_k[good], r_est[good], has_r[good], s_r[good]
        r_cost, s_cost = r_cost[good], s_cost[good]
        az, el = angles(vk)
        az_m, el_m = p.measured[kp, 0], p.measured[kp, 1]
        r0, r1 = wrap(az - az_m), el - el_m
        # S = J C J^T + diag(angular noise), J = d(az, el)/dx (gating.angle_jacobian,
        # whose J02 is 0)
        e, n, u = vk[:, 0], vk[:, 1], vk[:, 2]
        rho2 = np.maximum(e * e + n * n, 1e-12)
        rho = np.sqrt(rho2)
        r2 = rho2 + u * u
        j00, j01 = n / rho2, -e / rho2
        j10, j11, j12 = -u * e / (r2 * rho), -u * n / (r2 * rho), rho / r2
        floor2 = cfg.angle_floor_rad**2
        s00 = j00 * j00 * c00 + 2.0 * j00 * j01 * c01 + j01 * j01 * c11
        s00 += rays.sigma_az[rk] ** 2 + floor2
        s01 = j00 * (c00 * j10 + c01 * j11 + c02 * j12) + j01 * (c01 * j10 + c11 * j11 + c12 * j12)
        s11 = (
            j10 * j10 * c00
            + j11 * j11 * c11
            + j12 * j12 * c22
            + 2.0 * (j10 * j11 * c01 + j10 * j12 * c02 + j11 * j12 * c12)
        )
        s11 += rays.sigma_el[rk] ** 2 + floor2
        det = s00 * s11 - s01 * s01
        det = np.where(det > 0, det, 1e-30)
        stat = (r0 * r0 * s11 - 2 * r0 * r1 * s01 + r1 * r1 * s00) / det
        if cfg.range_in_cost:
            # the range residual joins the statistic: it separates signs along one ray
            stat = stat + np.where(
                has_r, ((rng_k - r_cost) / np.where(has_r, s_cost, 1.0)) ** 2, 0.0
            )
        chi2[k] = stat
    if rows is None:
        return chi2, ok
    full, plausible = np.full(p.ri.size, np.inf), np.zeros(p.ri.size, bool)
    full[rows], plausible[rows] = chi2, ok
    return full, plausible


def assign_per_image(
    n_rays: int, images: IntArray, ri: IntArray, li: IntArray, cost: Array, gate: float
) -> IntArray:
    """Best landmark per ray (-1 = none), no landmark used twice within one image.

    Pairs (ri, li) with ``cost`` above ``gate`` are not allowed.
    """
    out = np.full(n_rays, -1, np.int64)
    keep = cost <= gate
    ri, li, cost = ri[keep], li[keep], cost[keep]
    if ri.size == 0:
        return out
    img = images[ri]
    order = np.lexsort((cost, ri, img))
    ri, li, cost, img = ri[order], li[order], cost[order], img[order]
    # Fast path: in an image where the rays' best landmarks are all different, each ray
    # takes its best (that is the assignment's optimum); only the others need the solver.
    first = np.r_[True, ri[1:] != ri[:-1]]
    b_r, b_l, b_img = ri[first], li[first], img[first]
    o2 = np.lexsort((b_l, b_img))
    clash = (b_img[o2][1:] == b_img[o2][:-1]) & (b_l[o2][1:] == b_l[o2][:-1])
    slow_imgs = np.unique(b_img[o2][1:][clash])
    fast = ~np.isin(b_img, slow_imgs)
    out[b_r[fast]] = b_l[fast]
    slow = np.isin(img, slow_imgs)
    ri, li, cost, img = ri[slow], li[slow], cost[slow], img[slow]
    if ri.size == 0:
        return out
    bounds = np.flatnonzero(np.diff(img)) + 1
    for s, e in zip(np.r_[0, bounds], np.r_[bounds, ri.size], strict=True):
        r, lm, c = ri[s:e], li[s:e], cost[s:e]
        ur, rinv = np.unique(r, return_inverse=True)
        ul, linv = np.unique(lm, return_inverse=True)
        if ur.size == 1:
            out[ur[0]] = lm[0]  # sorted by cost within the ray: the best
            continue
        m = np.full((ur.size, ul.size), _BIG)
        np.minimum.at(m, (rinv, linv), c)
        rows, cols = min_cost_assignment(m)
        good = m[rows, cols] < _BIG
        out[ur[rows[good]]] = ul[cols[good]]
    return out


def assign_tracks(
    rays: LocalRays, ri: IntArray, li: IntArray, cost: Array, gate: float, link_gate: float
) -> tuple[IntArray, NDArray[np.bool_]]:
    """Best landmark per ray (-1 = none), tracks kept whole; and the rays of tracks that
    got a landmark but do not link to it.

    A track (rays with one ``track`` > 0: one sign followed through the images) takes the
    landmark that its rays gate to with the largest summed margin ``sum (gate - chi2)``,
    tracks seen together never the same landmark (:func:`_greedy_tracks`); its rays with
    ``chi2 <= link_gate`` against that landmark link to it, none to another. Untracked rays
    are assigned per image (:func:`assign_per_image`) among the landmarks no track holds in
    their image.

    >>> r = LocalRays(*np.zeros((2, 4, 3)), *np.ones((6, 4)), image=np.array([0, 1, 2, 1]),
    ...               sign_class=np.ones(4, np.int64), track=np.array([1, 1, 1, 2]))
    >>> ri, li = np.array([0, 1, 2, 2, 3]), np.array([0, 0, 0, 1, 0])
    >>> best, unlinked = assign_tracks(r, ri, li, np.array([1.0, 2.0, 20.0, 3.0, 0.5]), 10, 10)
    >>> best.tolist(), unlinked.tolist()
    ([0, 0, -1, -1], [False, False, True, False])
    """
    n, track = len(rays), rays.tracks
    tracked = track[ri] > 0
    best = np.full(n, -1, np.int64)
    unlinked = np.zeros(n, bool)
    keep = tracked & (cost <= gate)
    if keep.any():
        r, lm, c = ri[keep], li[keep], cost[keep]
        ut, tinv = np.unique(track[r], return_inverse=True)
        ul, linv = np.unique(lm, return_inverse=True)
        # summed margins per (track, landmark) that has pairs (sparse: a batch of many
        # units has many tracks and landmarks, few of them paired)
        cell, inv = np.unique(tinv * ul.size + linv, return_inverse=True)
        margin = np.zeros(cell.size)
        np.add.at(margin, inv, gate - c)
        chosen = _greedy_tracks(
            cell // ul.size, cell % ul.size, margin, track_spans(track, rays.image, ut), ul
        )
        # every ray of an assigned track, against its track's landmark
        pos, hit = _find(ut, track)
        ray_lm = np.where(hit, chosen[pos], -1)
        mine = tracked & (ray_lm[ri] == li)
        link = mine & (cost <= link_gate)
        best[ri[link]] = li[link]
        unlinked = (track > 0) & (ray_lm >= 0) & (best < 0)
        m = int(li.max()) + 1
        used = np.unique(rays.image[ri[link]] * m + li[link])
        free = ~tracked & ~np.isin(rays.image[ri] * m + li, used)
    else:
        free = ~tracked
    rest = assign_per_image(n, rays.image, ri[free], li[free], cost[free], gate)
    loose = track == 0
    best[loose] = rest[loose]
    return best, unlinked


def valid_tracks(track: ArrayLike, image: ArrayLike) -> IntArray:
    """``track`` with every track that holds two rays of one image set to 0 (untracked).

    One sign is detected at most once per image, so such a track is not one sign (a
    vehicle's tracker fault or a forged upload); it is not trusted to keep its rays
    together, and its rays are assigned per image like an older vehicle's.

    >>> valid_tracks([1, 1, 2, 2, 0, 0], [0, 1, 0, 0, 3, 3]).tolist()
    [1, 1, 0, 0, 0, 0]
    """
    t = np.asarray(track, np.int64)
    on = t > 0
    if not on.any():
        return t
    img = np.asarray(image, np.int64)[on]
    stride = int(img.max()) + 1  # one key per (track, image)
    key, count = np.unique(t[on] * stride + img, return_counts=True)
    return np.where(np.isin(t, key[count > 1] // stride), 0, t)


def track_spans(track: IntArray, image: IntArray, tracks: IntArray) -> IntArray:
    """(k, 2) first and last image of each of ``tracks`` (sorted ids) among the rays.

    >>> track_spans(np.array([3, 0, 3, 5]), np.array([4, 6, 9, 1]), np.array([3, 5])).tolist()
    [[4, 9], [1, 1]]
    """
    pos, mine = _find(tracks, track)
    lo = np.full(tracks.size, np.iinfo(np.int64).max)
    hi = np.full(tracks.size, np.iinfo(np.int64).min)
    np.minimum.at(lo, pos[mine], np.asarray(image, np.int64)[mine])
    np.maximum.at(hi, pos[mine], np.asarray(image, np.int64)[mine])
    return np.column_stack([lo, hi])


def _find(ids: IntArray, values: IntArray) -> tuple[IntArray, NDArray[np.bool_]]:
    """Position of each value in the sorted ``ids`` (clipped into range) and whether it is
    there (track ids are arbitrary u32 from the vehicle: looked up, not indexed).

    >>> [a.tolist() for a in _find(np.array([3, 5]), np.array([5, 0, 9]))]
    [[1, 0, 1], [True, False, False]]
    """
    pos = np.minimum(np.searchsorted(ids, values), ids.size - 1)
    return pos, ids[pos] == values


def _greedy_tracks(
    ti: IntArray, li: IntArray, margin: Array, span: IntArray, landmarks: IntArray
) -> IntArray:
    """Landmark per track (-1 = none) from the summed margins ``margin`` of (track ``ti``,
    landmark ``li``) cells, largest margins first; two tracks whose image spans overlap
    (two signs in view together) never share a landmark, two that follow each other (a
    track broken by a gap, or the sign passed again) may.

    >>> ti, li = np.array([0, 0, 1, 2]), np.array([0, 1, 0, 0])
    >>> m, span = np.array([5.0, 1.0, 4.0, 3.0]), np.array([[0, 9], [5, 12], [20, 30]])
    >>> _greedy_tracks(ti, li, m, span, np.array([7, 8])).tolist()
    [7, -1, 7]
    """
    chosen = np.full(span.shape[0], -1, np.int64)
    holders: dict[int, list[int]] = {}
    pos = margin > 0
    ti, li, margin = ti[pos], li[pos], margin[pos]
    for k in np.lexsort((li, ti, -margin)).tolist():
        t, j = int(ti[k]), int(li[k])
        if chosen[t] >= 0:
            continue
        others = holders.setdefault(j, [])
        if any(span[t, 0] <= span[o, 1] and span[o, 0] <= span[t, 1] for o in others):
            continue
        chosen[t] = landmarks[j]
        others.append(t)
    return chosen


@dataclass(frozen=True)
class Association:
    landmark: IntArray
    """Per ray, the index into the candidate landmarks (-1 = unmatched)."""
    chi2: Array
    offset: Array
    offset_cov: Array
    unlinked: NDArray[np.bool_] | None = None
    """Rays of tracks that went to a landmark without them (see :func:`assign_tracks`)."""
