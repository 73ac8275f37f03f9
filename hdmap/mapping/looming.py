"""Looming: how a panel's box grows as the car drives up says where the panel is along the
line of sight, whatever its size. O(1) sums per landmark that give, at any trial point,
how far beyond the panel the point lies.

With :mod:`hdmap.mapping.box_ranges`' relative range ``u(x) = d . (x - a) / r`` of a ray
and its inverse box range ``v = 1 / r``: a panel ``s`` times its class's nominal size at
``P`` gives ``r = t / s`` (``t`` the true distance), so at ``x = P + delta d``

    u = (t + delta) s / t = s + delta v,

exactly, for every ray of the panel: a straight line in ``v`` whose intercept is the
panel's size and whose **slope is the distance ``delta`` from the panel to ``x`` along
the rays**. The slope is fitted within each pass (about the pass's own mean ``v``) and
pooled over the passes, each by its spread in ``v``: only how each pass's boxes grow
counts, not how passes seen from different distances differ, since their shared errors
differ too (with the phones' errors a fit across passes put a landmark 8 m beyond its
sign 2 m short of it). A pass's shared origin error ``b`` tilts its rays' line by ``-d .
b``, so the slope's variance has ``tau^2 m2`` (:func:`offset`; about ``tau^2 / n`` for
``n`` passes alike) on top of the rays' white part ``1 / S``.

Pitfall: a box's relative height error ``e`` is in the regressor too (``v = s (1 + e) /
t``), which biases the slope by about ``s^2 sigma_e^2 mean(1/t) / var(1/t)``. Simulated
(8 head-on passes from 30-80 m to 10 m, boxes of 600 px m / distance): with 2 px of
noise on the box height the mean slope is 0.27 m off and ``t`` keeps its spread; with
4.24 px (42 % on a 10 px box at 60 m) 1.2 m off, ``t``'s mean square 2.1 and 1.75 % of
right landmarks past 3 (0.27 % under the model). A check at 3 sigma turns those into
candidates; a fusion would move them.

State (:func:`summed`): per pass, with ``h`` and ``w`` from
:func:`hdmap.mapping.box_ranges.ray_terms`, the slope's numerator about the pass's mean
``v`` (linear in the trial point), its denominator and what the pass's shared error does
to it; summed over passes, 6 numbers per landmark, kept in its home tile's frame. They add
when landmarks merge and follow a rigid change of frame (:func:`in_frame`).

>>> from hdmap.mapping import box_ranges
>>> a = np.array([[0.0, -60.0, 0.0], [0.0, -40.0, 0.0], [0.0, -20.0, 0.0], [0.0, -10.0, 0.0]])
>>> d = np.tile([0.0, 1.0, 0.0], (4, 1))  # looking North at a panel at the origin
>>> r = np.array([60.0, 40.0, 20.0, 10.0]) / 1.2  # a panel 1.2 times its nominal size
>>> h, w = box_ranges.ray_terms(a, d, r, r * 0.1, 0.5, 0.1)
>>> sums = summed(np.zeros(4, np.int64), np.zeros(4, np.int64), h, w)  # one pass
>>> delta, var, g, m2 = offset(sums, np.array([[0.0, 7.0, 0.0]]))  # 7 m beyond the panel
>>> round(float(delta[0]), 6), g.round(6).tolist(), round(float(m2[0]), 6)
(7.0, [[0.0, 1.0, 0.0]], 1.0)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping import box_ranges

Array = NDArray[np.float64]

N_SUMS = 6
"""Numbers a landmark keeps: over its passes ``sum_p N_p`` (4), ``sum_p S_p`` and ``sum_p
|N_p[:3]|^2`` (:func:`summed`)."""


RAW = 11
"""Numbers an open pass keeps (:func:`raw_terms` summed): ``sum w``, ``sum w v``, ``sum w
v^2``, ``sum w h[:4]``, ``sum w v h[:4]``; :func:`pass_sums` turns them into the pass's
share of a landmark's sums once all its rays are in."""


def raw_terms(h: Array, w: Array) -> Array:
    """Per ray its :data:`RAW` terms (n, 11) from its box-range terms ``h`` (n, 5) and
    weight ``w`` (n,; 0: adds nothing)."""
    hh = np.asarray(h, float).reshape(-1, 5)
    ww = np.asarray(w, float).reshape(-1)
    v = np.linalg.norm(hh[:, :3], axis=1)
    return np.concatenate(
        [
            np.stack([ww, ww * v, ww * v * v], 1),
            ww[:, None] * hh[:, :4],
            (ww * v)[:, None] * hh[:, :4],
        ],
        axis=1,
    )


def pass_sums(raw: ArrayLike) -> Array:
    """Each pass's share (k, ``N_SUMS``) of its landmark's sums from its raw sums (k,
    :data:`RAW`): about the pass's own weighted mean inverse range ``vbar``, ``N = sum w
    (v - vbar) h[:4]`` (``N . (x, 1)`` is the slope's numerator at ``x``), ``S = sum w (v -
    vbar)^2`` and ``|N[:3]|^2``."""
    per = np.asarray(raw, float).reshape(-1, RAW)
    with np.errstate(divide="ignore", invalid="ignore"):
        vbar = np.where(per[:, 0] > 0, per[:, 1] / per[:, 0], 0.0)
    n_p = per[:, 7:11] - vbar[:, None] * per[:, 3:7]
    return np.concatenate(
        [
            n_p,
            (per[:, 2] - vbar * per[:, 1])[:, None],
            np.einsum("ki,ki->k", n_p[:, :3], n_p[:, :3])[:, None],
        ],
        axis=1,
    )


def raw_in_frame(raw: ArrayLike, rot: Array | None, t: Array | None) -> Array:
    """Open passes' raw sums kept in frame F as they are in frame G (``x_G = rot x_F +
    t``)."""
    r = np.asarray(raw, float).reshape(-1, RAW)
    out = r.copy()
    zero = np.zeros((len(r), 1))
    for lo in (3, 7):
        padded = np.concatenate([r[:, lo : lo + 4], zero], axis=1)
        out[:, lo : lo + 4] = box_ranges.in_frame(padded, rot, t)[:, :4]
    return out


def summed(group: ArrayLike, piece: ArrayLike, h: Array, w: Array) -> Array:
    """Rays summed by the landmark each went to (``group``: 0, 1, ... per ray), (k,
    ``N_SUMS``); ``piece`` (0, 1, ... per ray) says which rays are one pass's (each piece
    within one group; :func:`pass_sums`). A pass cut into two pieces counts as two: each
    is centred on its own (unbiased, less precise: the slope within each piece only) and
    the pass's shared error's share is underestimated by the pieces' cross term."""
    g = np.asarray(group, np.int64).reshape(-1)
    pc = np.asarray(piece, np.int64).reshape(-1)
    npc = int(pc.max(initial=-1)) + 1
    per = np.zeros((npc, RAW))
    np.add.at(per, pc, raw_terms(h, w))
    owner = np.zeros(npc, np.int64)
    owner[pc] = g
    out = np.zeros((int(g.max(initial=-1)) + 1, N_SUMS))
    np.add.at(out, owner, pass_sums(per))
    return out


def in_frame(sums: ArrayLike, rot: Array | None, t: Array | None) -> Array:
    """Sums kept in frame F as they are in frame G, ``x_G = rot x_F + t`` (``N`` maps like
    a box-range ``h``; ``S`` and ``|N[:3]|^2`` do not change)."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    out = s.copy()
    padded = np.concatenate([s[:, :4], np.zeros((len(s), 1))], axis=1)
    out[:, :4] = box_ranges.in_frame(padded, rot, t)[:, :4]
    return out


def offset(sums: ArrayLike, x: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """(delta, var, g, m2) at trial points ``x`` (k, 3; the sums' frame): the fitted slope
    ``delta = N . (x, 1) / S`` (how far beyond the panel ``x`` lies along the rays,
    metres; NaN where no pass's inverse ranges spread), its white variance ``1 / S`` (from
    the rays' claimed weights), its gradient ``g = N[:3] / S`` (k, 3; about the near rays'
    line of sight, unit length) and ``m2 = sum_p |N_p[:3]|^2 / S^2`` (``-N_p[:3] . b /
    S`` is what an error ``b`` shared by pass ``p``'s rays does to ``delta``; ``m2 =
    |g|^2 / n`` for ``n`` passes alike)."""
    s = np.asarray(sums, float).reshape(-1, N_SUMS)
    x = np.asarray(x, float).reshape(-1, 3)
    den = np.where(s[:, 4] > 0, s[:, 4], np.nan)
    g = s[:, :3] / den[:, None]
    delta = np.einsum("ki,ki->k", g, x) + s[:, 3] / den
    return delta, 1.0 / den, g, s[:, 5] / den**2


def discrepancy(
    sums: ArrayLike, x: ArrayLike, cov: ArrayLike, tau_m: float
) -> tuple[Array, Array, Array]:
    """(t, g, spread): ``t = delta / sqrt(spread)``, ``spread = 1 / S + tau_m^2 m2 +
        g^T C g`` (:func:`offset`: the rays' white part, what the passes' shared position
        errors, ``tau_m`` per axis, do to the slope, and what the estimate's covariance ``C``
        (k x 3 x 3) lets ``delta`` move). With one panel at the estimate's place up to ``C``,
        ``t`` is about standard normal; NaN where no pass's inverse ranges spread. Where it is
    too large, :func:`hdmap.mapping.box_ranges.widened_along` with ``g`` and ``spread``."""
    delta, var, g, m2 = offset(sums, x)
    c = np.asarray(cov, float).reshape(-1, 3, 3)
    spread = var + tau_m**2 * m2 + np.einsum("ki,kij,kj->k", g, c, g)
    with np.errstate(invalid="ignore"):
        t = delta / np.sqrt(spread)
    return t, g, spread
