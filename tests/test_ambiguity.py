"""LAMBDA integer ambiguity resolution (estimator.ambiguity)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from estimator.ambiguity import (
    CandidateLimitError,
    IntegerSolution,
    decorrelate,
    enumerate_candidates_in_ellipsoid,
    integer_search,
    lambda_resolve,
    ldl_decompose,
    ratio_test,
)

WAVELENGTH_L1 = 0.19029367279836487  # m


# ------------------------------------------------------------------------------- helpers


def _line_of_sight(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Unit vectors receiver → satellite in NED."""
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)], axis=-1)


def _dd_covariance(
    rng: np.random.Generator,
    n: int,
    epochs: int = 10,
    sigma_phase: float = 0.005,
    sigma_code: float = 1.0,
) -> np.ndarray:
    """Float double-difference ambiguity covariance (cycles²) of a short static baseline.

    n + 1 satellites, L1 phase (σ in cycles) and code (σ in m) over a few 1 s epochs: the
    geometry barely changes, so the baseline comes mostly from code and the ambiguities are
    strongly correlated (an elongated Q, as in a real short-span float solution).
    """
    m = n + 1
    az = rng.uniform(0.0, 2.0 * np.pi, m)
    el = rng.uniform(np.radians(15.0), np.radians(85.0), m)
    rate = 1.45e-4  # rad/s, apparent angular rate of a GPS satellite
    d_az, d_el = rng.normal(size=m) * rate, rng.normal(size=m) * rate
    dd = np.hstack([-np.ones((n, 1)), np.eye(n)])  # reference satellite 0
    weight = np.linalg.inv(2.0 * dd @ dd.T)  # single differences between receivers, then DD
    normal = np.zeros((3 + n, 3 + n))
    for t in range(epochs):
        G = dd @ _line_of_sight(az + d_az * t, el + d_el * t)
        H_phase = np.hstack([G / WAVELENGTH_L1, np.eye(n)])
        H_code = np.hstack([G, np.zeros((n, n))])
        normal += H_phase.T @ weight @ H_phase / sigma_phase**2
        normal += H_code.T @ weight @ H_code / sigma_code**2
    Q = np.linalg.inv(normal)[3:, 3:]
    return 0.5 * (Q + Q.T)


def _random_covariance(rng: np.random.Generator, n: int) -> np.ndarray:
    """A correlated SPD matrix with eigenvalues between 0.03 and 1.5 cycles²."""
    R, _ = np.linalg.qr(rng.normal(size=(n, n)))
    eig = np.exp(rng.uniform(np.log(0.03), np.log(1.5), n))
    Q = R @ np.diag(eig) @ R.T
    return 0.5 * (Q + Q.T)


def _norms(cands: np.ndarray, a: np.ndarray, Q: np.ndarray) -> np.ndarray:
    r = cands - a
    return np.einsum("ij,ij->i", r @ np.linalg.inv(Q), r)


def _brute_force(a: np.ndarray, Q: np.ndarray, chi2: float) -> tuple[np.ndarray, np.ndarray]:
    """Every integer vector with norm ≤ chi2, from a box that bounds the ellipsoid."""
    half = np.sqrt(chi2 * np.diag(Q))
    axes = [np.arange(np.ceil(ai - h), np.floor(ai + h) + 1) for ai, h in zip(a, half, strict=True)]
    grid = np.array(list(itertools.product(*axes)), dtype=float).reshape(-1, len(a))
    norms = _norms(grid, a, Q)
    keep = norms <= chi2
    order = np.argsort(norms[keep])
    return grid[keep][order].astype(np.int64), norms[keep][order]


def _brute_force_best(a: np.ndarray, Q: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    # The norms of any `count` integer vectors bound the count-th best norm from above.
    base = np.round(a)
    trial = [base]
    for i in range(len(a)):
        for s in (-1.0, 1.0):
            trial.append(base + s * np.eye(len(a))[i])
    chi2 = np.sort(_norms(np.array(trial), a, Q))[count - 1]
    cands, norms = _brute_force(a, Q, chi2 * (1.0 + 1e-12))
    return cands[:count], norms[:count]


def _correlation_off_diagonal(Q: np.ndarray) -> np.ndarray:
    s = np.sqrt(np.diag(Q))
    R = Q / np.outer(s, s)
    return np.abs(R[~np.eye(len(Q), dtype=bool)])


# ------------------------------------------------------------------------- factorisation


@pytest.mark.parametrize("n", [1, 2, 5, 12])
def test_ldl_decompose_reconstructs_q(n: int) -> None:
    rng = np.random.default_rng(n)
    Q = _random_covariance(rng, n)
    L, D = ldl_decompose(Q)
    assert np.allclose(L.T @ np.diag(D) @ L, Q, rtol=0, atol=1e-13)
    assert np.array_equal(np.triu(L, 1), np.zeros((n, n)))
    assert np.allclose(np.diag(L), 1.0)
    assert np.all(D > 0)
    # D[i] is the variance of a_i given the later components: the last one is unconditioned.
    assert D[-1] == pytest.approx(Q[-1, -1])
    if n > 1:
        cond = Q[0, 0] - Q[0, 1:] @ np.linalg.solve(Q[1:, 1:], Q[1:, 0])
        assert D[0] == pytest.approx(cond)


# ------------------------------------------------------------------------- decorrelation


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_decorrelate_is_unimodular_and_decorrelates(seed: int) -> None:
    rng = np.random.default_rng(seed)
    Q = _dd_covariance(rng, 10)
    a = rng.normal(size=10) * 5.0
    Z, Qz, z = decorrelate(Q, a)

    assert Z.dtype.kind == "i"
    assert round(abs(np.linalg.det(Z.astype(float)))) == 1
    # The inverse is integer too (unimodular), so integer vectors map one-to-one.
    Zinv = np.linalg.inv(Z.astype(float))
    assert np.allclose(Zinv, np.round(Zinv), atol=1e-8)
    Zf = Z.astype(float)
    assert np.allclose(Qz, Zf.T @ Q @ Zf, rtol=0, atol=1e-12)
    assert np.allclose(z, Zf.T @ a)

    # Less correlated: smaller correlations, larger decorrelation number, far better condition.
    assert _correlation_off_diagonal(Qz).max() <= _correlation_off_diagonal(Q).max()

    def r(M: np.ndarray) -> float:
        return float(np.sqrt(np.linalg.det(M) / np.prod(np.diag(M))))

    assert r(Qz) >= r(Q)
    assert np.linalg.cond(Qz) < 1e-3 * np.linalg.cond(Q)

    # LAMBDA conditions on Qz = Lᵀ D L: |L[i, j]| ≤ 1/2 and no neighbour swap would help.
    L, D = ldl_decompose(Qz)
    assert np.abs(np.tril(L, -1)).max() <= 0.5 + 1e-9
    for k in range(9):
        assert D[k] + L[k + 1, k] ** 2 * D[k + 1] >= D[k + 1] * (1.0 - 1e-8)


def test_decorrelate_random_covariance_small_dimensions() -> None:
    rng = np.random.default_rng(11)
    for n in range(1, 7):
        Q = _random_covariance(rng, n)
        Z, Qz, _ = decorrelate(Q, np.zeros(n))
        assert round(abs(np.linalg.det(Z.astype(float)))) == 1
        assert np.allclose(Qz, Z.T @ Q @ Z, atol=1e-12)
        assert np.prod(np.diag(Qz)) <= np.prod(np.diag(Q)) * (1.0 + 1e-12)


# --------------------------------------------------------------------- exactness (search)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_best_and_second_match_brute_force(n: int) -> None:
    rng = np.random.default_rng(100 + n)
    for _ in range(25):
        Q = _random_covariance(rng, n)
        a = rng.normal(size=n) * 3.0
        sol = lambda_resolve(a, Q)
        cands, norms = _brute_force_best(a, Q, 2)
        assert np.array_equal(sol.integers, cands[0])
        assert np.array_equal(sol.second, cands[1])
        assert sol.squared_norms == pytest.approx(tuple(norms), rel=1e-9, abs=1e-12)
        assert sol.ratio == pytest.approx(norms[1] / norms[0], rel=1e-9)
        assert sol.ratio >= 1.0


@pytest.mark.parametrize("n", [2, 4])
def test_more_candidates_match_brute_force(n: int) -> None:
    rng = np.random.default_rng(200 + n)
    for _ in range(10):
        Q = _random_covariance(rng, n)
        a = rng.normal(size=n) * 3.0
        sol = lambda_resolve(a, Q, n_candidates=5)
        cands, norms = _brute_force_best(a, Q, 5)
        assert np.array_equal(sol.candidates, cands)
        assert np.allclose(sol.candidate_norms, norms, rtol=1e-9)
        # integer_search on the original (correlated) Q is exact as well, only slower.
        direct, direct_norms = integer_search(Q, a, n_candidates=5)
        assert np.array_equal(direct, cands)
        assert np.allclose(direct_norms, norms, rtol=1e-9)


def test_search_in_decorrelated_space_maps_back() -> None:
    rng = np.random.default_rng(5)
    Q = _dd_covariance(rng, 6, epochs=30, sigma_phase=0.02, sigma_code=0.3)
    a = rng.normal(size=6) * 10.0
    Z, Qz, z = decorrelate(Q, a)
    zc, znorms = integer_search(Qz, z)
    back = np.round(zc @ np.linalg.inv(Z.astype(float))).astype(np.int64)
    sol = lambda_resolve(a, Q)
    assert np.array_equal(back[0], sol.integers)
    assert np.array_equal(back[1], sol.second)
    assert np.allclose(znorms, sol.squared_norms, rtol=1e-8)
    assert np.allclose(_norms(back.astype(float), a, Q), znorms, rtol=1e-7)
    # Exact search without decorrelation (correlated tree, still tractable at n = 6) agrees.
    direct, _ = integer_search(Q, a)
    assert np.array_equal(direct, back)


# -------------------------------------------------------------------- known integers (GNSS)


@pytest.mark.parametrize(("n", "seed"), [(6, 2), (8, 3), (10, 4), (12, 5), (16, 6), (20, 7)])
def test_resolves_true_integers_from_dd_geometry(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    Q = _dd_covariance(rng, n)
    truth = rng.integers(-40, 40, n)
    a = truth + np.linalg.cholesky(Q) @ rng.normal(size=n)
    # The float solution alone is nowhere near the integers (code-dominated, ~1 cycle).
    assert np.sqrt(np.diag(Q)).max() > 0.3
    sol = lambda_resolve(a, Q)
    assert isinstance(sol, IntegerSolution)
    assert np.array_equal(sol.integers, truth)
    assert sol.success_rate > 0.999
    assert ratio_test(sol)
    assert np.allclose(sol.squared_norms[0], _norms(truth[None, :].astype(float), a, Q)[0])


def test_weak_geometry_is_flagged() -> None:
    # Five satellites over 10 s: LAMBDA still returns the ILS solution, but it is wrong here
    # and both validation figures say so.
    rng = np.random.default_rng(1)
    Q = _dd_covariance(rng, 4)
    truth = rng.integers(-40, 40, 4)
    a = truth + np.linalg.cholesky(Q) @ rng.normal(size=4)
    sol = lambda_resolve(a, Q)
    assert not np.array_equal(sol.integers, truth)
    assert sol.success_rate < 0.5
    assert not ratio_test(sol)


def test_dimension_one_and_thirty() -> None:
    sol = lambda_resolve(np.array([2.3]), np.array([[0.04]]))
    assert sol.integers.tolist() == [2] and sol.second.tolist() == [3]
    assert sol.squared_norms == pytest.approx((0.09 / 0.04, 0.49 / 0.04))
    assert sol.success_rate == pytest.approx(0.98758, abs=1e-5)  # 2Φ(0.5/0.2) − 1

    rng = np.random.default_rng(30)
    Q = _dd_covariance(rng, 30, epochs=10, sigma_phase=0.01, sigma_code=0.5)
    truth = rng.integers(-100, 100, 30)
    a = truth + np.linalg.cholesky(Q) @ rng.normal(size=30)
    sol = lambda_resolve(a, Q)
    assert np.array_equal(sol.integers, truth)


def test_large_ambiguity_values_are_exact() -> None:
    # Undifferenced-like ambiguities of millions of cycles: the result must shift exactly.
    rng = np.random.default_rng(8)
    Q = _dd_covariance(rng, 8)
    a = np.linalg.cholesky(Q) @ rng.normal(size=8)
    offset = rng.integers(-(10**7), 10**7, 8)
    near = lambda_resolve(a, Q)
    far = lambda_resolve(a + offset, Q)
    assert np.array_equal(far.integers, near.integers + offset)
    assert np.array_equal(far.second, near.second + offset)


def test_dimension_ten_strongly_correlated() -> None:
    # Correctness only: speed figures belong in benchmarks, not in timed tests.
    rng = np.random.default_rng(4)
    Q = _dd_covariance(rng, 10)
    assert 1e5 < np.linalg.cond(Q) < 1e8  # GNSS-like elongation
    truth = rng.integers(-40, 40, 10)
    chol = np.linalg.cholesky(Q)
    for _ in range(7):
        a = truth + chol @ rng.normal(size=10)
        assert np.array_equal(lambda_resolve(a, Q).integers, truth)


# ------------------------------------------------------------------------------ ratio test


def test_ratio_test_well_separated_accepts() -> None:
    rng = np.random.default_rng(21)
    Q = 0.002 * _random_covariance(rng, 5)
    truth = np.array([3, -7, 12, 0, 5])
    a = truth + np.linalg.cholesky(Q) @ rng.normal(size=5)
    sol = lambda_resolve(a, Q)
    assert np.array_equal(sol.integers, truth)
    assert sol.ratio > 10.0
    assert ratio_test(sol) and ratio_test(sol, threshold=10.0)
    assert sol.success_rate > 0.999


def test_ratio_test_half_integer_rejects() -> None:
    Q = np.array([[0.05, 0.01, 0.0], [0.01, 0.06, 0.02], [0.0, 0.02, 0.07]])
    # The first component between two integers: two candidates almost equally likely.
    a = np.array([4.5001, -2.0, 1.0])
    sol = lambda_resolve(a, Q)
    assert sol.ratio < 1.1
    assert not ratio_test(sol)
    assert {sol.integers[0], sol.second[0]} == {4, 5}
    assert sol.success_rate < 0.9
    with pytest.raises(ValueError, match="threshold"):
        ratio_test(sol, threshold=0.5)


def test_exact_integer_float_gives_infinite_ratio() -> None:
    sol = lambda_resolve(np.array([1.0, -2.0]), np.eye(2) * 0.1)
    assert sol.squared_norms[0] == 0.0
    assert sol.ratio == np.inf and ratio_test(sol)


# ------------------------------------------------------------------------------- ellipsoid


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_enumerate_matches_brute_force_n3(seed: int) -> None:
    rng = np.random.default_rng(300 + seed)
    Q = _random_covariance(rng, 3)
    a = rng.normal(size=3) * 4.0
    chi2 = 15.0
    got = enumerate_candidates_in_ellipsoid(a, Q, chi2)
    want, want_norms = _brute_force(a, Q, chi2)
    assert len(want) > 5
    assert got.shape == want.shape
    assert {tuple(v) for v in got} == {tuple(v) for v in want}
    assert np.allclose(_norms(got.astype(float), a, Q), want_norms)  # sorted by norm


def test_enumerate_dd_geometry_contains_truth_and_is_sorted() -> None:
    rng = np.random.default_rng(9)
    Q = _dd_covariance(rng, 6)
    truth = rng.integers(-20, 20, 6)
    a = truth + np.linalg.cholesky(Q) @ rng.normal(size=6)
    got = enumerate_candidates_in_ellipsoid(a, Q, chi2=200.0)
    norms = _norms(got.astype(float), a, Q)
    assert any(np.array_equal(v, truth) for v in got)
    assert np.all(np.diff(norms) >= -1e-9) and np.all(norms <= 200.0 + 1e-9)
    assert np.array_equal(got[0], lambda_resolve(a, Q).integers)


def test_enumerate_empty_and_limit() -> None:
    Q = np.eye(3) * 0.1
    a = np.array([0.5, 0.5, 0.5])  # every integer vector has norm ≥ 7.5
    assert enumerate_candidates_in_ellipsoid(a, Q, chi2=7.0).shape == (0, 3)
    assert len(enumerate_candidates_in_ellipsoid(a, Q, chi2=7.5 + 1e-9)) == 8
    with pytest.raises(CandidateLimitError, match="more than 5"):
        enumerate_candidates_in_ellipsoid(a, Q, chi2=100.0, limit=5)
    with pytest.raises(ValueError, match="chi2"):
        enumerate_candidates_in_ellipsoid(a, Q, chi2=-1.0)
    with pytest.raises(ValueError, match="limit"):
        enumerate_candidates_in_ellipsoid(a, Q, chi2=1.0, limit=0)


# ---------------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("Q", "a", "match"),
    [
        (np.array([[1.0, 0.2], [0.3, 1.0]]), np.zeros(2), "not symmetric"),
        (np.array([[1.0, 2.0], [2.0, 1.0]]), np.zeros(2), "not positive definite"),
        (np.array([[1.0, 1.0], [1.0, 1.0]]), np.zeros(2), "not positive definite"),
        (np.array([[-1.0]]), np.zeros(1), "not positive definite"),
        (np.array([[1.0, np.nan], [np.nan, 1.0]]), np.zeros(2), "NaN"),
        (np.eye(2), np.array([0.0, np.nan]), "NaN"),
        (np.eye(2), np.array([np.inf, 0.0]), "NaN or infinite"),
        (np.eye(3), np.zeros(2), "shape"),
        (np.eye(2), np.zeros((2, 1)), "shape"),
        (np.ones((2, 3)), np.zeros(2), "square"),
        (np.zeros((0, 0)), np.zeros(0), "empty"),
    ],
)
def test_invalid_input_raises(Q: np.ndarray, a: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        lambda_resolve(a, Q)
    with pytest.raises(ValueError, match=match):
        enumerate_candidates_in_ellipsoid(a, Q, chi2=1.0)


def test_invalid_arguments_raise() -> None:
    Q = np.eye(2)
    with pytest.raises(ValueError, match="not symmetric"):
        ldl_decompose(np.array([[1.0, 0.0], [0.5, 1.0]]))
    with pytest.raises(ValueError, match="n_candidates"):
        lambda_resolve(np.zeros(2), Q, n_candidates=1)
    with pytest.raises(ValueError, match="n_candidates"):
        integer_search(Q, np.zeros(2), n_candidates=0)
    with pytest.raises(ValueError, match="shape"):
        decorrelate(Q, np.zeros(3))
    # Rounding-level asymmetry (a filter's output) is tolerated.
    Qa = _random_covariance(np.random.default_rng(1), 3)
    Qa[0, 1] *= 1.0 + 1e-13
    lambda_resolve(np.zeros(3), Qa)
