"""Minimum-cost assignment of a rectangular cost matrix, numpy only.

The shortest augmenting path method (Crouse, "On implementing 2D rectangular assignment
algorithms", IEEE TAES 2016), step for step as ``scipy.optimize.linear_sum_assignment``
does it, including its choice among equal costs (columns scanned in reverse order, a
free column preferred on a tie), so that both give the same pairs on the same matrix.
It lives here so that the onboard tracker, which assigns detections to tracks with it,
needs no scipy; the matrices are small (the detections of one image).

>>> import numpy as np
>>> rows, cols = min_cost_assignment(np.array([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]]))
>>> rows.tolist(), cols.tolist()
([0, 1, 2], [1, 0, 2])
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

IntArray = NDArray[np.int64]


def min_cost_assignment(cost: ArrayLike) -> tuple[IntArray, IntArray]:
    """Rows and columns of an assignment of least total cost, ``min(n_rows, n_cols)`` pairs,
    rows in increasing order. Costs must be finite."""
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError("cost: expected a 2-d matrix")
    if c.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not np.isfinite(c).all():
        raise ValueError("cost: entries must be finite")
    transpose = c.shape[1] < c.shape[0]
    if transpose:
        c = c.T
    col4row = _solve(c)
    if transpose:
        order = np.argsort(col4row, kind="stable")
        return col4row[order], order.astype(np.int64)
    return np.arange(c.shape[0], dtype=np.int64), col4row


def _solve(c: NDArray[np.float64]) -> IntArray:
    nr, nc = c.shape
    u = np.zeros(nr)
    v = np.zeros(nc)
    col4row = np.full(nr, -1, np.int64)
    row4col = np.full(nc, -1, np.int64)
    path = np.full(nc, -1, np.int64)
    for cur in range(nr):
        spc = np.full(nc, np.inf)
        sr = np.zeros(nr, bool)
        sc = np.zeros(nc, bool)
        remaining = list(range(nc - 1, -1, -1))
        min_val = 0.0
        i = cur
        sink = -1
        while sink == -1:
            sr[i] = True
            rem = np.asarray(remaining, np.int64)
            r = min_val + c[i, rem] - u[i] - v[rem]
            better = r < spc[rem]
            path[rem[better]] = i
            spc[rem[better]] = r[better]
            s = spc[rem]
            lowest = s.min()
            at_min = np.flatnonzero(s == lowest)
            free = at_min[row4col[rem[at_min]] == -1]
            index = int(free[-1]) if free.size else int(at_min[0])
            min_val = float(lowest)
            j = remaining[index]
            if row4col[j] == -1:
                sink = j
            else:
                i = int(row4col[j])
            sc[j] = True
            remaining[index] = remaining[-1]
            remaining.pop()
        u[cur] += min_val
        others = sr.copy()
        others[cur] = False
        u[others] += min_val - spc[col4row[others]]
        v[sc] -= min_val - spc[sc]
        j = sink
        while True:
            i = int(path[j])
            row4col[j] = i
            col4row[i], j = j, int(col4row[i])
            if i == cur:
                break
    return col4row
