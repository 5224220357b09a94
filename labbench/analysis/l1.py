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
that does come back ends the steps. At a tied
(degenerate) vertex where no edge descends, a small LP over the tied rows
decides optimality.

Start: least squares, a few IRLS steps (weights 1/|r|), then the vertex
through small residuals whose rows are well apart (_initial_basis). Each step
costs a few passes over the data, and a handful of steps reach the certified
optimum, so the answer is the exact LAD vertex (to floating point), not a
point within a solver tolerance. The full dual LP (HiGHS) is the fallback if
the steps stall; its vertex is solved exactly and stepped from in turn.
"""
from __future__ import annotations

import numpy as np
from scipy import optimize

from labbench.errors import missing_extra

IRLS_STEPS = 6
MAX_STEPS = 500
XI_TOL = 1e-9
BASIS_TOL = 1e-4  # least new direction a row must bring to the initial basis (columns scaled to max 1)


def lad(X: np.ndarray, y: np.ndarray, theta0: np.ndarray | None = None) -> np.ndarray:
    """Exact l1 regression coefficients (see module doc); theta0 is an optional start.

    Columns that are linear combinations of earlier ones get coefficient 0.
    """
    X = np.asarray(X, float)
    y = np.asarray(y, float)
    keep = _independent_columns(X)
    if len(keep) < X.shape[1]:
        theta = np.zeros(X.shape[1])
        theta[keep] = lad(X[:, keep], y, None if theta0 is None else np.asarray(theta0)[keep])
        return theta
    theta = np.linalg.lstsq(X, y, rcond=None)[0] if theta0 is None else np.asarray(theta0, float)
    theta = _irls(X, y, theta, IRLS_STEPS)
    B = _initial_basis(X, np.abs(y - X @ theta))
    theta = _simplex(X, y, B)
    return _full_lp(X, y) if theta is None else theta


def _simplex(X, y, B):
    """Descent steps from basis B to the certified optimum (module doc); None if they stall."""
    seen: set[tuple[int, ...]] = set()
    peak = np.max(np.abs(y)), np.max(np.abs(X), axis=0)
    for _ in range(MAX_STEPS):
        if (key := tuple(sorted(B))) in seen:
            break  # a basis came back: a step "descended" by rounding only
        seen.add(key)
        try:
            theta = np.linalg.solve(X[B], y[B])
            r = y - X @ theta
            # residuals within rounding of zero are zero (a tie): left signed, a step
            # along an edge "descended" by 1e-16 and the next step came back (cycling)
            _zero_rounding(r, X, y, theta, peak)
            r[B] = 0.0  # exactly, so the basis rows never show up as breakpoints
            g = -(np.sign(r) @ X)
            xi = np.linalg.solve(X[B].T, g)
            if np.max(np.abs(xi)) <= 1.0 + XI_TOL:
                return theta
            U = np.linalg.solve(X[B], np.diag(-np.sign(xi)))  # column j: the edge leaving row B[j]
        except np.linalg.LinAlgError:
            break  # singular basis: leave it to the LP
        tie = r == 0.0
        tie[B] = False
        # slope of the objective along each edge at t = 0+: 1 - |xi_j|, plus |X_i u| for each
        # other zero residual (sign(0) = 0 left it out of xi); ties make a degenerate vertex
        slope = 1.0 - np.abs(xi) + np.abs(X[tie] @ U).sum(axis=0)
        j = int(np.argmin(slope))
        if slope[j] >= -XI_TOL:  # no edge of this basis descends
            if _certified(X, B, tie, g):
                return theta
            break  # a degenerate vertex that needs non-descending pivots: the LP does it
        a = X @ U[:, j]
        i_new = _line_search(r, a, -slope[j] / 2.0)
        if i_new < 0:
            break  # no breakpoint ahead: the basis solve overflowed (inf/nan residuals)
        B = B.copy()
        B[j] = i_new
    return None


def _zero_rounding(r, X, y, theta, peak):
    """Set to 0 the residuals r_i = y_i - X_i theta within rounding of zero (a few ulps of
    their largest term). Only residuals under a bound for all samples, from the peaks
    (max |y|, max |X_j|), are looked at: the per-sample bound over all n cost a fifth of
    the whole fit."""
    ulps = 16 * np.finfo(float).eps
    bound = ulps * (peak[0] + peak[1] @ np.abs(theta))
    near = np.flatnonzero(np.abs(r) <= bound)
    near = near[np.abs(r[near]) <= ulps * (np.abs(y[near]) + np.abs(X[near]) @ np.abs(theta))]
    r[near] = 0.0


def _initial_basis(X, absr) -> np.ndarray:
    """p rows with small residuals that are well apart (a well-conditioned basis).

    Gram-Schmidt over the rows in order of |r|, each column scaled by its largest
    magnitude: a row is taken if its part outside the span of the rows already
    taken has norm >= BASIS_TOL. (A rank test of the candidate rows alone is
    scale-free: rows at rest, whose filtered regressors are ~1e-317, pass it, and
    solving with them overflows to inf.) Only a prefix of the order is projected,
    grown as needed; a skipped row only loses norm to later projections, so it is
    never needed again.
    Later bases stay nonsingular by construction: an entering row has X_i u != 0.
    """
    n, p = X.shape
    scale = np.max(np.abs(X), axis=0)  # not a 2-norm: its squares could underflow
    order = np.argsort(absr)
    Q = np.zeros((0, p))  # orthonormal rows spanning the rows taken
    B: list[int] = []
    start, k = 0, 4 * p
    while len(B) < p:
        rows = order[start:start + k] if start < n else order
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


def _independent_columns(X) -> list[int]:
    """Columns, in order, that are not linear combinations of earlier kept ones.

    Ranks of columns scaled to largest magnitude 1: unscaled, a column far smaller
    than the next (units) made that next column look dependent and dropped it.
    """
    scale = np.max(np.abs(X), axis=0)
    Xs = X / np.where(scale > 0, scale, 1.0)
    keep: list[int] = []
    for j in range(X.shape[1]):
        if np.linalg.matrix_rank(Xs[:, keep + [j]]) == len(keep) + 1:
            keep.append(j)
    return keep


def _line_search(r, a, need):
    """Minimiser of sum_i |r_i - t a_i| along t > 0, whose slope starts at -2*need.

    Each breakpoint t_i = r_i / a_i > 0 raises the slope by 2|a_i|; the optimum is
    the first at which the raised slope reaches zero (a weighted median). Rows
    with r_i = 0 (basis, ties) are not breakpoints: ``need`` includes them.
    Only the smallest breakpoints are sorted, growing the batch as needed.
    Returns the sample index of that breakpoint, or -1 if there is none.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = r / a  # rows at rest (a ~ 1e-317) overflow to inf: excluded below
    cand = np.flatnonzero((t > 0) & np.isfinite(t))
    if len(cand) == 0:
        return -1
    tc, wc = t[cand], np.abs(a[cand])
    k = 64
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


def _certified(X, B, tie, g) -> bool:
    """Optimality at a degenerate vertex: signs s in [-1, 1] for all zero residuals
    (basis and ties) with sum_i s_i X_i = g, i.e. zero in the subdifferential.
    A feasibility LP over those few rows (HiGHS)."""
    T = np.r_[B, np.flatnonzero(tie)]
    res = optimize.linprog(np.zeros(len(T)), A_eq=X[T].T, b_eq=g, bounds=(-1, 1), method="highs")
    return res.status == 0


def objective(X, y, theta) -> float:
    return float(np.sum(np.abs(y - X @ theta)))


def _irls(X, y, theta, steps):
    """Iteratively reweighted least squares (weights 1/|r|, floored): a good start.

    Weights are relative to the mean |r| and floored at 1e6 (with the median as
    the scale, data fitted exactly at most samples got weights ~1e300, and tiny
    residuals overflow 1/|r|); the p x p normal equations go through lstsq,
    which takes a singular matrix (rows at rest) without raising.
    """
    for _ in range(steps):
        r = np.abs(y - X @ theta)
        scale = np.mean(r)
        if scale == 0:
            break  # an exact fit already
        Xw = X * (1.0 / np.maximum(r / scale, 1e-6))[:, None]
        theta = np.linalg.lstsq(X.T @ Xw, Xw.T @ y, rcond=None)[0]
    return theta


def _full_lp(X, y):
    """The dual LP max y.d s.t. X^T d = 0, |d| <= 1 (HiGHS), then its vertex exactly.

    Solved with y and the columns of X scaled to largest magnitude 1 (LAD is
    equivariant to both): HiGHS's tolerances are absolute, and with y ~ 6e-8 it
    answered a dual 50 % off. The equality marginals are theta only to the
    solver's tolerance, so the rows with |d_i| < 1, the zero residuals
    (complementary slackness), give a basis that is solved exactly and stepped
    from; its answer is taken unless it fits worse than the marginals.
    """
    ys = np.max(np.abs(y)) or 1.0
    xs = np.max(np.abs(X), axis=0)
    xs[xs == 0] = 1.0
    res = optimize.linprog(-y / ys, A_eq=(X / xs).T, b_eq=np.zeros(X.shape[1]), bounds=(-1, 1),
                           method="highs")
    if res.status != 0:
        raise RuntimeError(f"l1 LP failed: {res.message}")
    theta_lp = -np.asarray(res.eqlin.marginals, float) * ys / xs
    absr = np.abs(y - X @ theta_lp)
    absr[np.abs(res.x) >= 1.0 - 1e-7] = np.inf  # |d_i| = 1: not a zero residual, last in the order
    theta = _simplex(X, y, _initial_basis(X, absr))
    if theta is None or not np.all(np.isfinite(theta)) or objective(X, y, theta) > objective(X, y, theta_lp):
        return theta_lp
    return theta


def lad_cvxpy(X, y) -> np.ndarray:
    """The cross-check: cvxpy with its default solver."""
    try:
        import cvxpy as cp
    except ImportError:
        raise missing_extra("cvxpy", "cvxpy", "--solver cvxpy") from None

    theta = cp.Variable(X.shape[1])
    cp.Problem(cp.Minimize(cp.norm1(y - X @ theta))).solve()
    return np.asarray(theta.value, float)
