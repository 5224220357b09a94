"""Least absolute deviations  min_theta sum_i |y_i - X_i theta|, exactly and fast.

The optimum is a vertex: p samples fitted exactly (the basis B). It is
optimal iff xi solving X_B^T xi = -sum_{i not in B} sign(r_i) X_i has
|xi_j| <= 1 for all j (zero in the subdifferential). Otherwise moving off the
basis row j with |xi_j| > 1 lowers the objective at rate |xi_j| - 1 (less
|X_i u| for every other zero residual: a tie, e.g. from quantised data), and
the best step along the steepest such ray is the weighted median of the
breakpoints r_i / (X_i u) with weights |X_i u|: a simplex step with exact line
search, as in Barrodale & Roberts (1973, SIAM J. Numer. Anal. 10:839). In exact
arithmetic every step lowers the objective, so no basis comes back (no cycling);
in floating point, residuals within rounding of zero count as ties, and a basis
that does come back ends the steps. At a tied (degenerate) vertex, where more
than p residuals are zero and no edge of the basis descends, a small LP over the
tied rows (_tied_edge) finds a descending edge of another basis through the same
point, or proves that none exists (optimal). Without it, near-noise-free records
(a simulated chirp: residuals of 1e-13 beside forces of 1, ties at every few
steps) stalled at such vertices.

Start: least squares, a few IRLS steps (weights 1/|r|; both on at most START_ROWS rows,
a regular subset of a long record), then the vertex
through small residuals whose rows are well apart (_initial_basis). Each step
costs a few passes over the data, and a handful of steps reach the certified
optimum, so the answer is the exact LAD vertex (to floating point), not a
point within a solver tolerance. If the steps still stall, an LP over a working
set of rows (_working_set: constraint generation, a few hundred rows, not an LP
over all n samples, whose cost grew as n^2) takes over, and its vertex is solved
exactly and stepped from in turn.

Long records (GLOB_ROWS rows and more): the steps run over a band of rows near the fit,
the others held at their signs (_globbed), and the answer is still the exact LAD of
every row.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import optimize

from labbench.errors import missing_extra

IRLS_STEPS = 6
MAX_STEPS = 500
XI_TOL = 1e-9
START_ROWS = 1 << 17  # rows of the least-squares and IRLS start (a regular subset beyond)
BASIS_TOL = 1e-4  # least new direction a row must bring to the initial basis (columns scaled to max 1)
WS_ROWS = 32  # rows per parameter in the first working set of the fallback LP
QR_ROWS = 1 << 14  # rows per block of independent_columns' QR
GLOB_ROWS = 1 << 15  # from this many rows on, those far from the fit are globbed (_globbed)
GLOB_TRIES = 3  # bands tried, each GLOB_GROWTH x the last, before the fit over every row
GLOB_GROWTH = 4
GLOB_FIXES = 4  # times the rows that changed sign may join a band before it grows


def _no_check() -> None:
    pass


def lad(X: np.ndarray, y: np.ndarray, theta0: np.ndarray | None = None,
        check: Callable[[], None] | None = None) -> np.ndarray:
    """Exact l1 regression coefficients (see module doc); theta0 is an optional start.

    Columns that are linear combinations of earlier ones get coefficient 0. ``check`` is
    called between steps (each a few passes over the data): it may raise to stop the fit
    (``labbench.analysis.progress``).
    """
    check = check or _no_check
    # column-major: X @ theta on an n x p row-major array took 7x as long (OpenBLAS, p <= 4)
    X = np.asfortranarray(X, float)
    y = np.asarray(y, float)
    check()
    keep = independent_columns(X)
    check()
    if len(keep) < X.shape[1]:
        theta = np.zeros(X.shape[1])
        theta[keep] = lad(X[:, keep], y, None if theta0 is None else np.asarray(theta0)[keep], check)
        return theta
    if len(y) >= GLOB_ROWS:
        return _globbed(X, y, theta0, check)
    return _rows(X, y, theta0, check)


def _rows(X, y, theta0=None, check=_no_check):
    """LAD over every row of X (full column rank): the start, the steps, the working-set
    LP if they stall."""
    # the start needs no more rows than a 2-minute record has: beyond, a regular subset
    start = slice(None, None, max(1, len(y) // START_ROWS))
    if theta0 is None:
        theta = np.linalg.lstsq(X[start], y[start], rcond=None)[0]
        theta = _irls(X[start], y[start], theta, IRLS_STEPS, check)
    else:
        theta = np.asarray(theta0, float)
    vertex, certified = _simplex(X, y, _initial_basis(X, np.abs(y - X @ theta)), check)
    if certified:
        return vertex
    usable = vertex is not None and np.all(np.isfinite(y - X @ vertex))
    return _working_set(X, y, vertex if usable else theta, check)


def _globbed(X, y, theta0=None, check=_no_check):
    """LAD of a long record through a small problem: Portnoy & Koenker's preprocessing (1997,
    Statistical Science 12:279, section 3).

    A start (``theta0``, or the exact LAD of a regular subset of 2 n^(2/3) rows) leaves most
    residuals far from zero. Rows outside the band of the M smallest |r| are globbed: held
    at their signs s_i, they add sum_G s_i (y_i - X_i theta), a constant minus glob . theta
    with glob = sum_G s_i X_i, and the band's rows plus that linear term are stepped to
    their certified optimum (``_simplex``). Since |r_i| >= s_i r_i for every theta, that
    small objective is a lower bound of the whole one, equal to it wherever no globbed row
    has changed sign: when none has at its minimiser, that is the exact LAD of every row.
    Rows that did change sign join the band while they are few (a tenth of it, GLOB_FIXES
    times); else the band grows around the new fit (GLOB_GROWTH), as it does when the
    band's problem is unbounded (too few rows to balance the globbed ones) or its steps
    stall; after GLOB_TRIES bands every row is fitted. Each try costs a few passes over the
    data and steps over M = 4 n^(2/3) rows, so the whole fit's cost grows as n, not as n
    times the steps a longer record needs.
    """
    n = len(y)
    m = int(2 * n ** (2 / 3))
    if theta0 is None:
        sub = slice(None, None, max(1, n // m))
        theta = _rows(X[sub], y[sub], None, check)
    else:
        theta = np.asarray(theta0, float)
    band = 2 * m
    for _ in range(GLOB_TRIES):
        if band >= n // 2:
            break
        r = y - X @ theta
        absr = np.abs(r)
        near = absr <= np.partition(absr, band - 1)[band - 1]
        s = np.where(near, 0.0, np.sign(r))
        for _ in range(GLOB_FIXES):
            check()
            rows = np.flatnonzero(near)
            Xb, yb = X[rows], y[rows]
            vertex, certified = _simplex(Xb, yb, _initial_basis(Xb, absr[rows]), check, s @ X)
            if not certified:
                break  # unbounded (too few rows to balance the globbed ones) or stalled
            theta, r = vertex, y - X @ vertex
            wrong = s * r < 0
            if not wrong.any():
                return theta  # no globbed row changed sign: exact for all rows
            if wrong.sum() > len(rows) // 10:
                break
            near |= wrong  # a few changed sign: they join the band
            s[wrong] = 0.0
            absr = np.abs(r)
        band *= GLOB_GROWTH
    return _rows(X, y, theta, check)


def _simplex(X, y, B, check=_no_check, glob=None):
    """Descent steps from basis B to the certified optimum (module doc): (theta, True), or
    when they stall (the last vertex met, the lowest as every step descends, or None, False).
    ``glob``: the gradient of a linear term -glob . theta added to the objective (``_globbed``)."""
    glob = np.zeros(X.shape[1]) if glob is None else glob
    seen: set[tuple[int, ...]] = set()
    peak = np.max(np.abs(y)), np.max(np.abs(X), axis=0)
    theta = None
    for _ in range(MAX_STEPS):
        check()
        if (key := tuple(sorted(B))) in seen:
            break  # a basis came back: a step "descended" by rounding only
        seen.add(key)
        try:
            vertex = np.linalg.solve(X[B], y[B])
            if not np.all(np.isfinite(vertex)):
                break  # the basis solve overflowed (rows at rest)
            theta = vertex  # every step descends: the last vertex is the lowest met
            r = y - X @ theta
            # residuals within rounding of zero are zero (a tie): left signed, a step
            # along an edge "descended" by 1e-16 and the next step came back (cycling)
            tie = _zero_rounding(r, X, y, theta, peak)
            r[B] = 0.0  # exactly, so the basis rows never show up as breakpoints
            g = -(np.sign(r) @ X + glob)
            xi = np.linalg.solve(X[B].T, g)
            if np.max(np.abs(xi)) <= 1.0 + XI_TOL:
                return theta, True
            U = np.linalg.solve(X[B], np.diag(-np.sign(xi)))  # column j: the edge leaving row B[j]
        except np.linalg.LinAlgError:
            break  # singular basis: leave it to the working-set LP
        tie = np.setdiff1d(tie, B)
        # slope of the objective along each edge at t = 0+: 1 - |xi_j|, plus |X_i u| for each
        # other zero residual (sign(0) = 0 left it out of xi); ties make a degenerate vertex
        slope = 1.0 - np.abs(xi) + np.abs(X[tie] @ U).sum(axis=0)
        j = int(np.argmin(slope))
        if slope[j] < -XI_TOL:
            keep, u, need = np.delete(B, j), U[:, j], -slope[j] / 2.0
        else:  # no edge of this basis descends: at a tied vertex another basis's edge may
            edge = _tied_edge(X, B, tie, g)
            if edge is None:
                return theta, True  # certified: zero is in the subdifferential
            if not edge:
                break
            keep, u, need = edge
        i_new = _line_search(r, X @ u, need)
        if i_new < 0:
            break  # no breakpoint ahead: the basis solve overflowed (inf/nan residuals)
        B = np.append(keep, i_new)
    return theta, False


def _zero_rounding(r, X, y, theta, peak):
    """Set to 0 the residuals r_i = y_i - X_i theta within rounding of zero (a few ulps of
    their largest term) and return their indices. Only residuals under a bound for all samples, from the peaks
    (max |y|, max |X_j|), are looked at: the per-sample bound over all n cost a fifth of
    the whole fit."""
    ulps = 16 * np.finfo(float).eps
    bound = ulps * (peak[0] + peak[1] @ np.abs(theta))
    near = np.flatnonzero(np.abs(r) <= bound)
    near = near[np.abs(r[near]) <= ulps * (np.abs(y[near]) + np.abs(X[near]) @ np.abs(theta))]
    r[near] = 0.0
    return near


def _initial_basis(X, absr) -> np.ndarray:
    """p rows with small residuals that are well apart (a well-conditioned basis).

    Gram-Schmidt over the rows in order of |r|, each column scaled by its largest
    magnitude: a row is taken if its part outside the span of the rows already
    taken has norm >= BASIS_TOL. (A rank test of the candidate rows alone is
    scale-free: rows at rest, whose filtered regressors are ~1e-317, pass it, and
    solving with them overflows to inf.) Only a prefix of the order is projected,
    grown as needed; a skipped row only loses norm to later projections, so it is
    never needed again. Only that prefix is sorted (``_smallest``): a sort of all n
    residuals cost n log n, a seventh of a 30-minute record's fit.
    Later bases stay nonsingular by construction: an entering row has X_i u != 0.
    """
    n, p = X.shape
    scale = np.max(np.abs(X), axis=0)  # not a 2-norm: its squares could underflow
    Q = np.zeros((0, p))  # orthonormal rows spanning the rows taken
    B: list[int] = []
    start, k = 0, 4 * p
    while len(B) < p:
        rows = _smallest(absr, start + k)[start:] if start < n else _smallest(absr, n)
        R = X[rows] / scale
        for _ in range(2):  # projected twice: once leaves ~eps/(new part) of the old directions
            R = R - (R @ Q.T) @ Q
        norms = np.linalg.norm(R, axis=1)
        ok = np.flatnonzero(norms >= BASIS_TOL)
        if start >= n:  # no row is far enough out (nearly dependent columns): take the farthest
            ok = [int(np.argmax(norms))]
        elif len(ok) == 0:
            start, k = start + k, 4 * k
            continue
        i = int(ok[0])
        B.append(int(rows[i]))
        Q = np.vstack([Q, R[i] / (norms[i] or 1.0)])  # 0: dependent columns, the LP takes over
        start += i + 1 if start < n else 0
    return np.array(B)


def _smallest(a, k) -> np.ndarray:
    """Indices of the k smallest entries of ``a`` in ascending order, ties in index order:
    the first k of a stable argsort of ``a``, without sorting the rest."""
    if k >= len(a):
        return np.argsort(a, kind="stable")
    kth = np.partition(a, k - 1)[k - 1]
    if np.isnan(kth):  # NaNs sort last: the prefix reaches them
        return np.argsort(a, kind="stable")[:k]
    below = np.flatnonzero(a <= kth)  # index order: the stable sort keeps it among ties
    return below[np.argsort(a[below], kind="stable")][:k]


def independent_columns(X) -> list[int]:
    """Columns, in order, that are not linear combinations of earlier kept ones.

    Ranks of columns scaled to largest magnitude 1: unscaled, a column far smaller
    than the next (units) made that next column look dependent and dropped it. The ranks
    are those of the R factor of a QR of X, its columns scaled after (Householder QR is
    backward stable column by column, and the singular values of X[:, cols] are those of
    R[:, cols]): a copy and p SVDs of all n rows cost a fifth of a long record's fit.
    The QR goes QR_ROWS rows at a time, each block's R stacked on the next block (a
    tall-skinny QR: the same R up to signs; one QR of all rows left the cache, 20x the time
    for 15x the rows). The tolerance is numpy's matrix_rank's: largest singular value x n x eps.
    """
    n, p = X.shape
    scale = np.maximum(X.max(axis=0), -X.min(axis=0))  # max |X_j| without an |X| copy
    R = np.zeros((0, p))
    for i in range(0, n, QR_ROWS):
        R = np.linalg.qr(np.vstack([R, X[i:i + QR_ROWS]]), mode="r")
    R = R / np.where(scale > 0, scale, 1.0)
    keep: list[int] = []
    for j in range(p):
        sv = np.linalg.svd(R[:, keep + [j]], compute_uv=False)
        if len(sv) == len(keep) + 1 and sv[-1] > sv[0] * max(n, len(sv)) * np.finfo(float).eps:
            keep.append(j)
    return keep


def _line_search(r, a, need):
    """Minimiser of sum_i |r_i - t a_i| along t > 0, whose slope starts at -2*need.

    Each breakpoint t_i = r_i / a_i > 0 raises the slope by 2|a_i|; the optimum is
    the first at which the raised slope reaches zero (a weighted median). Rows
    with r_i = 0 (basis, ties) are not breakpoints: ``need`` includes them.
    Only the smallest breakpoints are sorted, growing the batch as needed (a long record's
    step passes more of them).
    Returns the sample index of that breakpoint, or -1 if there is none.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = r / a  # rows at rest (a ~ 1e-317) overflow to inf: excluded below
    cand = np.flatnonzero((t > 0) & np.isfinite(t))
    if len(cand) == 0:
        return -1
    tc, wc = t[cand], np.abs(a[cand])
    # first batch: twice the breakpoints of average weight that ``need`` takes (64 at least)
    mean_w = float(np.mean(wc))
    k = len(tc) if 2.0 * need >= len(tc) * mean_w else max(64, int(2.0 * need / mean_w))
    while True:
        if k >= len(tc):
            order = np.argsort(tc)
        else:
            part = np.argpartition(tc, k)[:k]
            order = part[np.argsort(tc[part])]
        c = np.cumsum(wc[order])
        if c[-1] >= need or k >= len(tc):
            return int(cand[order[min(np.searchsorted(c, need), len(order) - 1)]])
        k *= 4


def _tied_edge(X, B, tie, g):
    """At a tied (degenerate) vertex, whose zero residuals Z (basis and ties) outnumber p:
    a descending edge, or None when there is none (the vertex is optimal).

    Along a direction u the objective changes at the rate g.u + sum_Z |X_i u|. The small LP
    min sum_Z |X_i u| s.t. g.u = -1 (HiGHS, over the rows of Z only) finds the steepest
    such direction; its minimum >= 1 means no direction descends (its dual is zero in the
    subdifferential: signs in [-1, 1] on Z with sum s_i X_i = g). Its vertex keeps p - 1
    rows of Z at zero: an edge, recomputed exactly as the null vector of those rows.
    Returns (the p - 1 rows kept, u, need) for the line search, None when certified, or ()
    when no edge can be trusted (the LP's or the edge's numbers at rounding level).
    """
    Z = np.r_[B, tie]
    p, nz = X.shape[1], len(Z)
    if not np.any(g):
        return None
    scale = np.max(np.abs(X[Z]), axis=0)
    scale[scale == 0] = 1.0
    XZ = X[Z] / scale  # columns scaled: HiGHS's tolerances are absolute
    gs = g / scale
    gs_norm = np.max(np.abs(gs))
    # variables (u, t): min sum t s.t. |XZ u| <= t, (gs / |gs|) u = -1
    A_ub = np.block([[XZ, -np.eye(nz)], [-XZ, -np.eye(nz)]])
    res = optimize.linprog(np.r_[np.zeros(p), np.ones(nz)], A_ub=A_ub, b_ub=np.zeros(2 * nz),
                           A_eq=np.r_[gs / gs_norm, np.zeros(nz)][None, :], b_eq=[-1.0],
                           bounds=[(None, None)] * p + [(0, None)] * nz, method="highs")
    if res.status != 0:
        return ()  # numerical trouble: no edge to trust
    if res.fun >= gs_norm * (1.0 - XI_TOL):
        return None
    us = res.x[:p]
    a = np.abs(XZ @ us) / np.maximum(np.linalg.norm(XZ, axis=1) * np.linalg.norm(us), 1e-300)
    keep = _independent_rows(XZ, np.argsort(a), p - 1)
    if keep is None:
        return ()
    u = (np.linalg.svd(XZ[keep])[2][-1] if len(keep) else us) / scale  # null vector of the kept rows
    u *= -np.sign(g @ u) or 1.0
    slope = g @ u + np.abs(X[Z] @ u).sum()
    if not slope < -XI_TOL * (np.abs(g) @ np.abs(u)):
        return ()  # the exact edge does not descend: rounding at the LP's tolerance
    return Z[keep], u, -slope / 2.0


def _independent_rows(A, order, k):
    """The first k rows of A in ``order`` each with a part outside the span of those before
    it of at least BASIS_TOL of its norm (Gram-Schmidt, projected twice); None if fewer."""
    taken, Q = [], np.zeros((0, A.shape[1]))
    for i in order:
        if len(taken) == k:
            break
        v = A[i]
        for _ in range(2):
            v = v - (v @ Q.T) @ Q
        norm = np.linalg.norm(v)
        if norm >= BASIS_TOL * np.linalg.norm(A[i]) and norm > 0:
            taken.append(int(i))
            Q = np.vstack([Q, v / norm])
    return np.array(taken, int) if len(taken) == k else None


def objective(X, y, theta) -> float:
    return float(np.sum(np.abs(y - X @ theta)))


def _irls(X, y, theta, steps, check=_no_check):
    """Iteratively reweighted least squares (weights 1/|r|, floored): a good start.

    Weights are relative to the mean |r| and floored at 1e6 (with the median as
    the scale, data fitted exactly at most samples got weights ~1e300, and tiny
    residuals overflow 1/|r|); the p x p normal equations go through lstsq,
    which takes a singular matrix (rows at rest) without raising.
    """
    for _ in range(steps):
        check()
        r = np.abs(y - X @ theta)
        scale = np.mean(r)
        if scale == 0:
            break  # an exact fit already
        Xw = X * (1.0 / np.maximum(r / scale, 1e-6))[:, None]
        theta = np.linalg.lstsq(X.T @ Xw, Xw.T @ y, rcond=None)[0]
    return theta


def _working_set(X, y, theta, check=_no_check):
    """LAD from theta when the steps stall, by an LP over a working set S of rows (constraint
    generation): each round costs a few passes over the data and an LP of |S| rows, never
    one of all n (which grew as n^2: 19 s at 90 000 samples).

    With the rows outside S held at their signs s_i at theta,
    f(theta + d) >= sum_S |r_i - X_i d| - c.d + const, c = sum_{i not in S} s_i X_i, with
    equality while no outside row changes sign; so where the minimiser of that bound changes
    no outside sign, it minimises f itself. Its dual, max r_S.d s.t. X_S^T d = -c, |d| <= 1,
    is solved (HiGHS) with the residuals and the columns scaled to largest magnitude 1 (its
    tolerances are absolute); infeasible means the bound is unbounded below, and S grows.
    Each round S takes the WS_ROWS x p rows of smallest |r| (doubling every round, so S
    reaches all rows only if every smaller set fails), the zero residuals and the rows
    whose sign changed. The equality marginals are the step only to the solver's
    tolerance, so the vertex through the rows of S it fits best is solved exactly and
    stepped from; its answer is taken unless it fits worse.
    """
    n, p = X.shape
    xs = np.max(np.abs(X), axis=0)
    xs[xs == 0] = 1.0
    r = y - X @ theta
    f = np.sum(np.abs(r))
    S = np.zeros(n, bool)
    k = min(n, WS_ROWS * p)
    while True:
        check()
        S[np.argpartition(np.abs(r), k - 1)[:k] if k < n else slice(None)] = True
        S |= r == 0.0  # a zero residual outside S would be left out of the bound
        s = np.where(S, 0.0, np.sign(r))
        rs = np.max(np.abs(r[S])) or 1.0
        res = optimize.linprog(-r[S] / rs, A_eq=(X[S] / xs).T, b_eq=-(s @ X) / xs, bounds=(-1, 1),
                               method="highs")
        if res.status == 0:
            step = -np.asarray(res.eqlin.marginals, float) * rs / xs
            r_new = y - X @ (theta + step)
            flipped = s * r_new < 0
            if (f_new := np.sum(np.abs(r_new))) <= f:
                theta, r, f = theta + step, r_new, f_new
            if not flipped.any():
                break
            S |= flipped
        elif k == n:
            raise RuntimeError(f"l1 LP failed: {res.message}")
        k = min(n, 2 * k)
    absr = np.abs(r)
    absr[~S] = np.inf  # outside rows are not zero residuals: last in the order
    vertex, _ = _simplex(X, y, _initial_basis(X, absr), check)
    if vertex is None or not np.all(np.isfinite(vertex)) or objective(X, y, vertex) > f:
        return theta
    return vertex


def lad_cvxpy(X, y) -> np.ndarray:
    """The cross-check: cvxpy with its default solver."""
    try:
        import cvxpy as cp
    except ImportError:
        raise missing_extra("cvxpy", "cvxpy", "--solver cvxpy") from None

    theta = cp.Variable(X.shape[1])
    cp.Problem(cp.Minimize(cp.norm1(y - X @ theta))).solve()
    return np.asarray(theta.value, float)
