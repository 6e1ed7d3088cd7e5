"""Integer ambiguity resolution by the LAMBDA method (Teunissen; thesis 3.2.2).

Given a float ambiguity vector ``â`` (cycles) with covariance ``Q``, the integer least-squares
solution minimises ``(a - â)ᵀ Q⁻¹ (a - â)`` over integer vectors ``a``. The steps are:

1. ``Q = Lᵀ D L`` with ``L`` unit lower triangular, factorised from the last index backwards
   (as in the LAMBDA papers), so ``D[i]`` is the variance of ``a_i`` conditioned on
   ``a_{i+1} .. a_{n-1}`` and the search runs from the last component to the first.
2. Decorrelation ``z = Zᵀ a``, ``Q_z = Zᵀ Q Z`` with a unimodular integer ``Z`` built from integer
   Gauss transformations (make ``|L[i, j]| ≤ 1/2``) and permutations of neighbours (move small
   conditional variances to the end), which makes the search tree narrow.
3. A depth-first search of the ellipsoid in the ``z`` space, visiting integers of each level in
   order of increasing distance from the conditional estimate (Schnorr–Euchner zig-zag) and
   shrinking the ellipsoid whenever enough candidates are held. The search is exact: it returns
   the true minimisers of the quadratic form over the integer lattice.
4. Back-transformation ``a = Z⁻ᵀ z`` (exact in integer arithmetic).

All ambiguities are in cycles; ``Q`` in cycles².
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Relative tolerance of the symmetry check of Q (covariances often come out of a filter with
# rounding asymmetry of a few ulp).
_SYMMETRY_RTOL = 1e-8
# A permutation must decrease the conditional variance by more than this fraction; this keeps
# the reduction from cycling on (numerically) equal variances.
_SWAP_RTOL = 1e-10


@dataclass(frozen=True)
class IntegerSolution:
    """Result of :func:`lambda_resolve` (integers in the original, not the decorrelated, space)."""

    integers: np.ndarray  # best integer vector
    second: np.ndarray  # second-best integer vector
    squared_norms: tuple[float, float]  # (a-â)ᵀ Q⁻¹ (a-â) of best and second
    ratio: float  # second / best (≥ 1; inf when the float vector is exactly integer)
    success_rate: float  # bootstrapping success rate from the decorrelated conditional variances
    # All candidates of the search, best first (n_candidates rows) and their squared norms.
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    candidate_norms: np.ndarray = field(default_factory=lambda: np.zeros(0))


class CandidateLimitError(ValueError):
    """More integer vectors lie inside the requested ellipsoid than the caller allowed."""


# --------------------------------------------------------------------------------- checks


def _check_covariance(Q: np.ndarray) -> np.ndarray:
    Q = np.asarray(Q, dtype=float)
    if Q.ndim != 2 or Q.shape[0] != Q.shape[1]:
        raise ValueError(f"ambiguity covariance must be a square matrix, got shape {Q.shape}")
    if Q.shape[0] == 0:
        raise ValueError("ambiguity covariance is empty (no ambiguities to resolve)")
    if not np.all(np.isfinite(Q)):
        raise ValueError("ambiguity covariance contains NaN or infinite entries")
    scale = float(np.max(np.abs(Q)))
    if np.max(np.abs(Q - Q.T)) > _SYMMETRY_RTOL * scale:
        raise ValueError("ambiguity covariance is not symmetric")
    # Remove the tolerated rounding asymmetry so every later step sees an exactly symmetric Q.
    return 0.5 * (Q + Q.T)


def _check_float(a: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 1 or a.shape[0] != n:
        raise ValueError(
            f"float ambiguity vector must have shape ({n},) to match the covariance, got {a.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise ValueError("float ambiguity vector contains NaN or infinite entries")
    return a


# ------------------------------------------------------------------------- factorisation


def _ltdl(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Q = Lᵀ diag(D) L for an already checked symmetric Q."""
    n = Q.shape[0]
    A = Q.copy()
    L = np.zeros((n, n))
    D = np.zeros(n)
    for i in range(n - 1, -1, -1):
        d = A[i, i]
        # The pivot is the conditional variance of a_i given a_{i+1..}: it is positive for every
        # i exactly when Q is positive definite. A pivot lost in rounding noise is singular too.
        if not d > 1e-14 * abs(Q[i, i]):
            raise ValueError(
                "ambiguity covariance is not positive definite "
                f"(conditional variance {d:.3g} at index {i})"
            )
        D[i] = d
        row = A[i, : i + 1] / d
        L[i, : i + 1] = row
        # Schur complement: condition the remaining components on a_i.
        A[:i, :i] -= np.outer(row[:i], A[i, :i])
    return L, D


def ldl_decompose(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Factorise ``Q = Lᵀ diag(D) L`` with ``L`` unit lower triangular.

    Returns ``(L, D)`` with ``D`` the vector of the diagonal; ``D[i]`` is the variance of the
    i-th component conditioned on all later ones. Raises ValueError if ``Q`` is not a finite,
    symmetric, positive definite square matrix.
    """
    return _ltdl(_check_covariance(Q))


# --------------------------------------------------------------------------- decorrelation


def _reduce(L: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Decorrelate: returns (Z, Z⁻¹, L_z, D_z) with Zᵀ Lᵀ diag(D) L Z = L_zᵀ diag(D_z) L_z."""
    n = D.shape[0]
    # Plain Python lists: the work is many short scalar updates, where NumPy's per-call overhead
    # dominates; Python integers also make Z exact without any overflow concern.
    Lr = L.tolist()  # rows of L
    Dl = D.tolist()
    Zc = [[int(i == j) for i in range(n)] for j in range(n)]  # columns of Z
    Zi = [[int(i == j) for j in range(n)] for i in range(n)]  # rows of Z⁻¹
    # LLL-like sweep from the end. Invariants at pair (k, k+1): the pairs after it have their
    # conditional variances in order, and the columns after k are size-reduced (|L[i, j]| ≤ 1/2)
    # exactly when j ≥ clean_from. Reducing a whole column before its pair is tested keeps the
    # entries of L bounded through the permutations (reducing only L[k+1, k] lets them explode).
    clean_from = n - 1
    k = n - 2
    while k >= 0:
        if k < clean_from:
            for i in range(k + 1, n):
                # Integer Gauss transformation Z ← Z (I − μ e_i e_kᵀ): column k of L and Z lose
                # μ times column i; the rows above i are untouched.
                mu = math.floor(Lr[i][k] + 0.5)
                if mu:
                    for r in range(i, n):
                        row = Lr[r]
                        row[k] -= mu * row[i]
                    Zc[k] = [x - mu * y for x, y in zip(Zc[k], Zc[i], strict=True)]
                    Zi[i] = [x + mu * y for x, y in zip(Zi[i], Zi[k], strict=True)]
            clean_from = k
        rk, rk1 = Lr[k], Lr[k + 1]
        lk = rk1[k]
        d_k, d_k1 = Dl[k], Dl[k + 1]
        delta = d_k + lk * lk * d_k1  # variance of a_k given a_{k+2..}
        if delta < (1.0 - _SWAP_RTOL) * d_k1:
            # Swap components k and k+1: the smaller conditional variance moves to the end.
            eta = d_k / delta
            lam = d_k1 * lk / delta
            Dl[k] = eta * d_k1
            Dl[k + 1] = delta
            for j in range(k):
                u, v = rk[j], rk1[j]
                rk[j] = v - lk * u
                rk1[j] = eta * u + lam * v
            rk1[k] = lam
            for r in range(k + 2, n):
                row = Lr[r]
                row[k], row[k + 1] = row[k + 1], row[k]
            Zc[k], Zc[k + 1] = Zc[k + 1], Zc[k]
            Zi[k], Zi[k + 1] = Zi[k + 1], Zi[k]
            # Column k+1 now holds the reduced old column k; column k changed.
            clean_from = k + 1
            # The swap may have broken the order of the pair above.
            k = min(k + 1, n - 2)
        else:
            k -= 1
    # The sweep ends after testing pair 0 with column 0 reduced: every column is reduced now.
    big = max(max(abs(x) for x in col) for col in Zc)
    if big >= 2**62:
        raise ValueError(
            "decorrelation needs integers beyond int64 (covariance too ill-conditioned)"
        )
    Z = np.array(Zc, dtype=np.int64).T
    Zinv = np.array(Zi, dtype=np.int64)
    return Z, Zinv, np.array(Lr), np.array(Dl)


def decorrelate(Q: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LAMBDA decorrelation: ``(Z, Qz, z)`` with ``Qz = Zᵀ Q Z`` and ``z = Zᵀ a``.

    ``Z`` is an integer (int64) matrix with ``|det Z| = 1``, so integer vectors map one-to-one
    onto integer vectors and ``a = Z⁻ᵀ z``.
    """
    Q = _check_covariance(Q)
    a = _check_float(a, Q.shape[0])
    L, D = _ltdl(Q)
    Z, _, _, _ = _reduce(L, D)
    Zf = Z.astype(float)
    Qz = Zf.T @ Q @ Zf
    return Z, 0.5 * (Qz + Qz.T), Zf.T @ a


# ---------------------------------------------------------------------------------- search


def _search(
    L: np.ndarray,
    D: np.ndarray,
    zhat: np.ndarray,
    n_best: int,
    radius: float = math.inf,
    limit: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth-first ellipsoid search on Q = Lᵀ diag(D) L.

    With ``limit`` None: the ``n_best`` integer vectors of smallest squared norm (not above
    ``radius``), the ellipsoid shrinking to the worst one held. With ``limit``: every vector with
    squared norm ≤ ``radius`` (fixed ellipsoid), CandidateLimitError beyond ``limit`` of them.
    Returns (candidates (m, n) int64, squared norms (m,)), sorted by norm.
    """
    n = D.shape[0]
    collect_all = limit is not None
    # Plain Python lists: the loop is scalar work, where NumPy element access is slow.
    Lt = L.T.tolist()  # Lt[k][j] = L[j, k]: weight of level j's residual in level k's estimate
    Dl = D.tolist()
    z = [0] * n  # current integers
    e = [0.0] * n  # z[j] − conditional estimate of level j
    zb = [0.0] * n  # conditional estimates
    step = [0] * n
    dist = [0.0] * n  # dist[k]: partial norm of the levels above k
    # T[k][j] = ẑ_k + Σ_{i ≥ j} L[i, k] e_i, so the conditional estimate of level k is T[k][k+1].
    # The partial sums of level k are valid for j > stale[k]; only those invalidated by changes
    # of the levels above are recomputed, which makes a node cost O(1) on average instead of
    # O(n) (the trick of Ghasemmehdi & Agrell's faster sphere-decoding recursions).
    T = [[0.0] * n + [float(zhat[k])] for k in range(n)]
    stale = [n - 1] * n
    found: list[tuple[float, list[int]]] = []
    max_dist = radius

    k = n
    new_dist = 0.0
    descend = True
    while True:
        if descend:
            # Enter level k − 1 at the integer nearest to its conditional estimate.
            k -= 1
            if k < n - 1:
                dist[k] = new_dist
            Tk = T[k]
            Lk = Lt[k]
            s = stale[k]
            for j in range(s, k, -1):
                Tk[j] = Tk[j + 1] + Lk[j] * e[j]
            stale[k] = k
            if k > 0 and stale[k - 1] < s:
                stale[k - 1] = s
            c = Tk[k + 1]
            zi = math.floor(c + 0.5)
            zb[k] = c
            z[k] = zi
            y = c - zi
            step[k] = 1 if y >= 0.0 else -1
        else:
            # Next integer of level k, zig-zagging away from the conditional estimate.
            si = step[k]
            z[k] += si
            step[k] = -si - 1 if si > 0 else -si + 1
            y = zb[k] - z[k]
        e[k] = -y
        if k > 0 and stale[k - 1] < k:
            stale[k - 1] = k
        new_dist = dist[k] + y * y / Dl[k] if k < n - 1 else y * y / Dl[k]
        if new_dist <= max_dist if collect_all else new_dist < max_dist:
            if k > 0:
                descend = True
                continue
            max_dist = _keep(found, new_dist, z, n_best, radius, limit, max_dist)
            descend = False
        else:
            # Every further integer of this level is farther away: back to the level above.
            if k == n - 1:
                break
            k += 1
            descend = False

    found.sort(key=lambda f: f[0])
    cands = np.array([f[1] for f in found], dtype=np.int64).reshape(len(found), n)
    return cands, np.array([f[0] for f in found], dtype=float)


def _keep(found: list[tuple[float, list[int]]], dist: float, z: list[int], n_best: int,
          radius: float, limit: int | None, max_dist: float) -> float:
    """A full integer vector inside the current ellipsoid joins ``found`` (all of them up to
    ``limit``, else the ``n_best`` nearest); returns the ellipsoid's new squared radius."""
    if limit is not None:
        found.append((dist, z.copy()))
        if len(found) > limit:
            raise CandidateLimitError(f"more than {limit} integer vectors inside the ellipsoid "
                                      f"(chi2 = {radius:g}); lower chi2 or raise the limit")
        return max_dist
    if len(found) < n_best:
        found.append((dist, z.copy()))
        return min(radius, max(f[0] for f in found)) if len(found) == n_best else max_dist
    worst = max(range(n_best), key=lambda i: found[i][0])
    found[worst] = (dist, z.copy())
    return min(radius, max(f[0] for f in found))


def integer_search(
    Qz: np.ndarray, z: np.ndarray, n_candidates: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Exact integer least-squares search in the (decorrelated) space.

    Returns ``(candidates, squared_norms)``: an ``(n_candidates, k)`` int64 array of the integer
    vectors with the smallest ``(z - ẑ)ᵀ Qz⁻¹ (z - ẑ)``, best first, and those norms. Exact for
    any positive definite ``Qz``; fast when ``Qz`` is decorrelated (see :func:`decorrelate`).
    """
    if int(n_candidates) != n_candidates or n_candidates < 1:
        raise ValueError(f"n_candidates must be a positive integer, got {n_candidates}")
    Qz = _check_covariance(Qz)
    z = _check_float(z, Qz.shape[0])
    L, D = _ltdl(Qz)
    # Search the fractional part: keeps the arithmetic small for large float ambiguities.
    base = np.floor(z + 0.5)
    cands, norms = _search(L, D, z - base, int(n_candidates))
    return cands + base.astype(np.int64), norms


# ---------------------------------------------------------------------------- resolution


def _bootstrap_success_rate(D: np.ndarray) -> float:
    # P = Π (2Φ(1 / (2σ_i)) − 1) with σ_i² the decorrelated conditional variances.
    return float(np.prod([math.erf(1.0 / (2.0 * math.sqrt(2.0 * d))) for d in D]))


def _prepare(
    a_float: np.ndarray, Q: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Checks, then (integer offset, Z⁻¹, L_z, D_z, ẑ of the fractional part)."""
    Q = _check_covariance(Q)
    a = _check_float(a_float, Q.shape[0])
    # Split off the nearest integers so the transformed floats stay small: large raw ambiguities
    # (1e6 cycles and more) would otherwise lose the fractional part in Zᵀ a.
    base = np.floor(a + 0.5)
    L, D = _ltdl(Q)
    Z, Zinv, Lz, Dz = _reduce(L, D)
    zhat = Z.T.astype(float) @ (a - base)
    return base.astype(np.int64), Zinv, Lz, Dz, zhat


def lambda_resolve(a_float: np.ndarray, Q: np.ndarray, n_candidates: int = 2) -> IntegerSolution:
    """Integer least-squares ambiguity resolution (LAMBDA).

    ``a_float``: float ambiguities (cycles), ``Q``: their covariance (cycles²). Returns the best
    and second-best integer vectors, their squared norms, the ratio second/best and the
    bootstrapping success rate. ``n_candidates`` ≥ 2 candidates are searched and kept in
    ``solution.candidates``.
    """
    if int(n_candidates) != n_candidates or n_candidates < 2:
        raise ValueError(f"n_candidates must be an integer ≥ 2, got {n_candidates}")
    base, Zinv, Lz, Dz, zhat = _prepare(a_float, Q)
    zc, norms = _search(Lz, Dz, zhat, int(n_candidates))
    # a = Z⁻ᵀ z, exact in integers.
    cands = zc @ Zinv + base
    best, second = float(norms[0]), float(norms[1])
    ratio = second / best if best > 0.0 else math.inf
    return IntegerSolution(
        integers=cands[0].copy(),
        second=cands[1].copy(),
        squared_norms=(best, second),
        ratio=ratio,
        success_rate=_bootstrap_success_rate(Dz),
        candidates=cands,
        candidate_norms=norms,
    )


def ratio_test(solution: IntegerSolution, threshold: float = 3.0) -> bool:
    """Accept the fixed solution when second-best / best squared norm ≥ ``threshold``."""
    if not threshold >= 1.0:
        raise ValueError(f"ratio test threshold must be ≥ 1, got {threshold}")
    return bool(solution.ratio >= threshold)


def enumerate_candidates_in_ellipsoid(
    a_float: np.ndarray, Q: np.ndarray, chi2: float, limit: int = 10000
) -> np.ndarray:
    """All integer vectors ``a`` with ``(a - â)ᵀ Q⁻¹ (a - â) ≤ chi2``, sorted by that norm.

    Returns an ``(m, n)`` int64 array (m may be 0). The enumeration runs in the decorrelated
    space and stops with CandidateLimitError (a ValueError) as soon as more than ``limit``
    vectors are found, so a too large ``chi2`` fails early instead of building a huge set.
    """
    if not (math.isfinite(chi2) and chi2 >= 0.0):
        raise ValueError(f"chi2 must be a finite non-negative number, got {chi2}")
    if int(limit) != limit or limit < 1:
        raise ValueError(f"limit must be a positive integer, got {limit}")
    base, Zinv, Lz, Dz, zhat = _prepare(a_float, Q)
    zc, _ = _search(Lz, Dz, zhat, 0, radius=float(chi2), limit=int(limit))
    return zc @ Zinv + base
