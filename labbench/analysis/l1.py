"""Least absolute deviations  min_theta sum_i |y_i - X_i theta|, exactly and fast.

The optimum is a vertex: p samples fitted exactly (the basis B). It is
optimal iff xi solving X_B^T xi = -sum_{i not in B} sign(r_i) X_i has
|xi_j| <= 1 for all j (zero in the subdifferential). Otherwise moving off the
basis row with the largest |xi_j| lowers the objective at rate |xi_j| - 1, and
the best step along that ray is the weighted median of the breakpoints
r_i / (X_i u) with weights |X_i u|: a simplex step with exact line search,
as in Barrodale & Roberts (1973, SIAM J. Numer. Anal. 10:839).

Start: least squares, a few IRLS steps (weights 1/|r|), then the vertex
through the p smallest residuals. Each step costs a few passes over the data,
and a handful of steps reach the certified optimum, so the answer is the exact
LAD vertex (to floating point), not a point within a solver tolerance. The
full dual LP (HiGHS) is the fallback if the steps stall.
"""
from __future__ import annotations

import numpy as np
from scipy import optimize

IRLS_STEPS = 6
MAX_STEPS = 500
XI_TOL = 1e-9


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
    p = X.shape[1]
    theta = np.linalg.lstsq(X, y, rcond=None)[0] if theta0 is None else np.asarray(theta0, float)
    theta = _irls(X, y, theta, IRLS_STEPS)
    B = _initial_basis(X, np.abs(y - X @ theta))
    for _ in range(MAX_STEPS):
        try:
            theta = np.linalg.solve(X[B], y[B])
            r = y - X @ theta
            r[B] = 0.0  # exactly, so the basis rows never show up as breakpoints
            xi = np.linalg.solve(X[B].T, -(np.sign(r) @ X))
        except np.linalg.LinAlgError:
            break  # singular basis: leave it to the LP
        j = int(np.argmax(np.abs(xi)))
        if abs(xi[j]) <= 1.0 + XI_TOL:
            return theta
        e = np.zeros(p)
        e[j] = -np.sign(xi[j])
        u = np.linalg.solve(X[B], e)
        a = X @ u
        a[B] = 0.0
        a[B[j]] = e[j]
        i_new = _line_search(r, a, (abs(xi[j]) - 1.0) / 2.0)
        if i_new in B:
            break  # degenerate: no progress possible along this edge
        B = B.copy()
        B[j] = i_new
    return _full_lp(X, y)


def _initial_basis(X, absr) -> np.ndarray:
    """p rows with small residuals that span the columns (a nonsingular basis).

    Later bases stay nonsingular by construction: an entering row has X_i u != 0.
    """
    p = X.shape[1]
    order = np.argsort(absr)
    B: list[int] = []
    for i in order:
        if np.linalg.matrix_rank(X[B + [i]]) == len(B) + 1:
            B.append(int(i))
            if len(B) == p:
                break
    return np.array(B)


def _independent_columns(X) -> list[int]:
    keep: list[int] = []
    for j in range(X.shape[1]):
        if np.linalg.matrix_rank(X[:, keep + [j]]) == len(keep) + 1:
            keep.append(j)
    return keep


def _line_search(r, a, need):
    """Minimiser of sum_i |r_i - t a_i| along t > 0, whose slope starts at -2*need.

    Each breakpoint t_i = r_i / a_i > 0 raises the slope by 2|a_i|; the optimum is
    the first at which the raised slope reaches zero (a weighted median).
    Only the smallest breakpoints are sorted, growing the batch as needed.
    Returns the sample index of that breakpoint.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t = r / a
    cand = np.flatnonzero((t > 0) & np.isfinite(t))
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


def objective(X, y, theta) -> float:
    return float(np.sum(np.abs(y - X @ theta)))


def _irls(X, y, theta, steps):
    """Iteratively reweighted least squares (weights 1/|r|, floored): a good start."""
    for _ in range(steps):
        r = np.abs(y - X @ theta)
        w = 1.0 / np.maximum(r, 1e-6 * (np.median(r) + 1e-300))
        Xw = X * w[:, None]
        theta = np.linalg.solve(X.T @ Xw, Xw.T @ y)
    return theta


def _full_lp(X, y):
    """Dual LP max y.d s.t. X^T d = 0, |d| <= 1 (HiGHS); theta are the equality marginals."""
    res = optimize.linprog(-y, A_eq=X.T, b_eq=np.zeros(X.shape[1]), bounds=(-1, 1), method="highs")
    if res.status != 0:
        raise RuntimeError(f"l1 LP failed: {res.message}")
    return -np.asarray(res.eqlin.marginals, float)


def lad_cvxpy(X, y) -> np.ndarray:
    """The cross-check: cvxpy with its default solver."""
    import cvxpy as cp

    theta = cp.Variable(X.shape[1])
    cp.Problem(cp.Minimize(cp.norm1(y - X @ theta))).solve()
    return np.asarray(theta.value, float)
