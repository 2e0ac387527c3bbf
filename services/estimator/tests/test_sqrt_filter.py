"""The square-root Kalman filter: FilterPy's answers where both are exact; stable where not."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from focustrack_estimator.sqrt_filter import SqrtKalmanFilter, psd_factor


def _wiener2(dx: float, q: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F, Q, H of a Wiener order-2 height model (height, slope, curvature) with step dx."""
    F = np.array([[1.0, dx, dx * dx / 2.0], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
    return F, Q_discrete_white_noise(3, dt=dx, var=q), np.array([[1.0, 0.0, 0.0]])


def _is_positive_definite(P: np.ndarray) -> bool:
    return bool(np.all(np.diag(P) > 0) and np.linalg.eigvalsh((P + P.T) / 2).min() > 0)


def test_agrees_with_filterpy_on_a_well_conditioned_problem() -> None:
    rng = np.random.default_rng(3)
    F, Q, H = _wiener2(dx=1.0, q=0.05)
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.x, kf.P = np.array([[1.0], [0.0], [0.0]]), np.diag([100.0, 1.0, 0.1])
    sq = SqrtKalmanFilter(dim_x=3, dim_z=1)
    sq.x, sq.P = kf.x.copy(), kf.P.copy()
    for step in range(60):
        # per-step overrides, as the strategies call them; every 7th tile has no measurement
        kf.predict(F=F, Q=Q)
        sq.predict(F=F, Q=Q)
        np.testing.assert_allclose(sq.x, kf.x, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(sq.P, kf.P, rtol=1e-9, atol=1e-12)
        z = None if step % 7 == 3 else np.array([[np.sin(step / 5.0) + rng.normal(0, 0.5)]])
        R = 0.25 + 0.05 * (step % 3)
        kf.update(z, R=R, H=H)
        sq.update(z, R=R, H=H)
        np.testing.assert_allclose(sq.x, kf.x, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(sq.P, kf.P, rtol=1e-9, atol=1e-12)
        if z is not None:
            np.testing.assert_allclose(sq.y, kf.y, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(sq.S, kf.S, rtol=1e-10)
            np.testing.assert_allclose(sq.K, kf.K, rtol=1e-9, atol=1e-12)
            assert sq.log_likelihood == pytest.approx(kf.log_likelihood, rel=1e-10)
            assert sq.mahalanobis == pytest.approx(kf.mahalanobis, rel=1e-10)
    np.testing.assert_allclose(sq.P_post, kf.P_post, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sq.P_prior, kf.P_prior, rtol=1e-9, atol=1e-12)


def test_rectangular_transition_grows_the_state() -> None:
    """The 2-D strategies append a tile to the state: F of shape (n + 1, n)."""
    sq = SqrtKalmanFilter(dim_x=2, dim_z=1)
    sq.x, sq.P = np.array([[1.0], [3.0]]), np.array([[2.0, 0.5], [0.5, 1.0]])
    P_before = sq.P
    F = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])  # the new element predicts from both
    Q = np.diag([0.0, 0.0, 0.3])  # rank one: noise enters the new element only
    sq.predict(F=F, Q=Q)
    np.testing.assert_allclose(sq.x.ravel(), [1.0, 3.0, 2.0])
    np.testing.assert_allclose(sq.P, F @ P_before @ F.T + Q, rtol=1e-12)


def test_rank_deficient_covariances_are_factored() -> None:
    _, Q, _ = _wiener2(dx=200.0, q=0.01)  # rank one, with round-off making it indefinite
    assert np.linalg.eigvalsh(Q).min() < 0
    L = psd_factor(Q)
    assert np.allclose(np.triu(L, 1), 0.0)
    np.testing.assert_allclose(L @ L.T, Q, rtol=0, atol=1e-9 * np.abs(Q).max())


def test_square_root_form_stays_positive_definite_where_the_covariance_form_does_not() -> None:
    """Steps in micrometres (dx = 200 um per tile) and a tiny R (thesis ch. 3, observability).

    The covariance form, both the textbook (I - K H) P (lecture notes eq. 4.82,
    thesis Algorithm 1) and FilterPy's Joseph form, computes an indefinite P;
    the square-root form keeps a factor with a positive diagonal and matches a
    reference computed in extended precision.
    """
    F, Q, H = _wiener2(dx=200.0, q=0.01)
    R, P0 = 1e-10, np.diag([1e2, 1.0, 1e-2])
    measurements = np.random.default_rng(0).normal(0.0, 1.0, 60)

    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.F, kf.Q, kf.H, kf.R, kf.P = F, Q, H, np.array([[R]]), P0.copy()
    sq = SqrtKalmanFilter(dim_x=3, dim_z=1)
    sq.F, sq.Q, sq.H, sq.R, sq.P = F, Q, H, R, P0
    P_plain = P0.copy()
    ld = np.longdouble  # reference: Joseph form in extended precision
    x_ref, P_ref = np.zeros((3, 1), dtype=ld), P0.astype(ld)

    plain_broken = joseph_broken = 0
    for z in measurements:
        kf.predict()
        kf.update(np.array([[z]]))
        sq.predict()
        sq.update(z)
        P_plain = F @ P_plain @ F.T + Q
        K = P_plain @ H.T / (H @ P_plain @ H.T + R)
        P_plain = (np.eye(3) - K @ H) @ P_plain
        plain_broken += not _is_positive_definite(P_plain)
        joseph_broken += not _is_positive_definite(kf.P)

        assert np.all(np.diag(sq.P_sqrt) > 0), "the factor must keep a positive diagonal"
        assert (
            np.array_equal(sq.P, sq.P.T) or np.abs(sq.P - sq.P.T).max() < 1e-15 * np.abs(sq.P).max()
        )

        x_ref, P_ref = F.astype(ld) @ x_ref, F.astype(ld) @ P_ref @ F.T.astype(ld) + Q.astype(ld)
        K_ref = P_ref @ H.T.astype(ld) / ((H.astype(ld) @ P_ref @ H.T.astype(ld))[0, 0] + ld(R))
        x_ref = x_ref + K_ref * (ld(z) - x_ref[0, 0])
        A = np.eye(3, dtype=ld) - K_ref @ H.astype(ld)
        P_ref = A @ P_ref @ A.T + K_ref @ K_ref.T * ld(R)

    assert plain_broken > 0 and joseph_broken > 0, "the covariance form should break here"
    if np.finfo(np.longdouble).eps < np.finfo(float).eps:
        np.testing.assert_allclose(np.diag(sq.P), np.diag(P_ref).astype(float), rtol=1e-5)
        scale = np.sqrt(np.diag(P_ref).astype(float))
        assert np.all(np.abs((sq.x - x_ref.astype(float)).ravel()) < 1e-6 * scale)


def test_bad_shapes_are_rejected() -> None:
    sq = SqrtKalmanFilter(dim_x=2, dim_z=1)
    with pytest.raises(ValueError, match="do not fit"):
        sq.predict(F=np.eye(3), Q=1.0)
    with pytest.raises(ValueError, match="do not fit"):
        sq.update(1.0, R=1.0, H=np.ones((1, 3)))
    with pytest.raises(ValueError, match="NaN"):
        sq.P = np.array([[np.nan, 0.0], [0.0, 1.0]])
