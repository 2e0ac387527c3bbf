"""State-space models: F and Q against the thesis' equations and FilterPy, PSD, observability."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise, Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.linalg import solve_discrete_are

from focustrack_core.geometry import Step
from focustrack_estimator.models import (
    DirectionAwareModel,
    GaussMarkovModel,
    WienerModel,
    gauss_markov_process_noise,
    gauss_markov_transition,
    observability_matrix,
    observability_rank,
    taylor_transition,
    wiener_process_noise,
)

MOVES = (Step.PLUS_X, Step.MINUS_X, Step.PLUS_Y)


def assert_symmetric_psd(Q: np.ndarray) -> None:
    np.testing.assert_allclose(Q, Q.T, atol=0)
    assert np.linalg.eigvalsh(Q).min() >= -1e-12 * np.abs(Q).max()


def all_models() -> list:
    return [
        WienerModel(0, 0.2),
        WienerModel(1, 1e-3, q_height_um2=0.05),
        WienerModel(2, 1e-5),
        GaussMarkovModel(1, 1.0, 6.0),
        GaussMarkovModel(2, 0.5, 21.0, q_height_um2=0.1),
        DirectionAwareModel(1e-3),
        DirectionAwareModel(1e-3, q_height_um2=0.05, partitioned=False),
    ]


def test_wiener_q_is_equation_3_30() -> None:
    expected = np.array([[1 / 20, 1 / 8, 1 / 6], [1 / 8, 1 / 3, 1 / 2], [1 / 6, 1 / 2, 1.0]])
    np.testing.assert_allclose(wiener_process_noise(2, 0.7), 0.7 * expected)
    np.testing.assert_allclose(wiener_process_noise(0, 0.7), [[0.7]])


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("dx", [1.0, 0.5, 2.0])
def test_wiener_q_matches_filterpy_continuous_white_noise(order: int, dx: float) -> None:
    expected = Q_continuous_white_noise(dim=order + 1, dt=dx, spectral_density=0.3)
    np.testing.assert_allclose(wiener_process_noise(order, 0.3, dx), expected)


def test_wiener_q_and_filterpy_discrete_white_noise_share_the_gradient_terms() -> None:
    # Piecewise-constant noise (FilterPy's discrete model) and integrated white noise
    # (thesis eq. 3-30) agree on the gradient terms; only the height variance differs.
    discrete = Q_discrete_white_noise(dim=2, dt=1.0, var=0.3)
    continuous = wiener_process_noise(1, 0.3)
    np.testing.assert_allclose(continuous[1:, :], discrete[1:, :])
    np.testing.assert_allclose([continuous[0, 0], discrete[0, 0]], [0.3 / 3, 0.3 / 4])


def test_taylor_transition_is_equation_3_23() -> None:
    np.testing.assert_allclose(
        taylor_transition(2), [[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]]
    )


@pytest.mark.parametrize("model", all_models(), ids=lambda m: type(m).__name__)
def test_every_q_is_symmetric_psd(model) -> None:
    for step in MOVES:
        transition = model.transition(step)
        assert transition.F.shape == transition.Q.shape == (model.n_states, model.n_states)
        assert_symmetric_psd(transition.Q)
    assert_symmetric_psd(model.initial_covariance(10.0))


def test_reversed_step_flips_the_odd_derivative_terms() -> None:
    forward, backward = wiener_process_noise(2, 1.0, 1.0), wiener_process_noise(2, 1.0, -1.0)
    signs = np.array([[1, -1, 1], [-1, 1, -1], [1, -1, 1]])
    np.testing.assert_allclose(backward, signs * forward)
    assert_symmetric_psd(backward)


def test_direction_aware_model_is_equations_3_54_and_3_55() -> None:
    model = DirectionAwareModel(q=2.0)
    plus_x, minus_x, plus_y = (model.transition(step) for step in MOVES)
    np.testing.assert_allclose(plus_x.F, [[1, 1, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(minus_x.F, [[1, -1, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(plus_y.F, [[1, 0, 1], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(
        plus_x.Q, 2.0 * np.array([[1 / 3, 1 / 2, 0], [1 / 2, 1, 0], [0, 0, 0]])
    )
    np.testing.assert_allclose(
        minus_x.Q, 2.0 * np.array([[1 / 3, -1 / 2, 0], [-1 / 2, 1, 0], [0, 0, 0]])
    )
    np.testing.assert_allclose(
        plus_y.Q, 2.0 * np.array([[1 / 3, 0, 1 / 2], [0, 0, 0], [1 / 2, 0, 1]])
    )
    # Partitioned update (Algorithm 2): only the height and the gradient along the step.
    assert plus_x.updated.tolist() == [True, True, False]
    assert plus_y.updated.tolist() == [True, False, True]
    assert DirectionAwareModel(2.0, partitioned=False).transition(Step.PLUS_Y).updated.all()


def test_height_noise_enters_at_the_height_only() -> None:
    plain = WienerModel(1, 1e-3).transition(Step.PLUS_X).Q
    noisy = WienerModel(1, 1e-3, q_height_um2=0.25).transition(Step.PLUS_X).Q
    np.testing.assert_allclose(noisy - plain, [[0.25, 0.0], [0.0, 0.0]])


def test_start_step_is_no_move() -> None:
    transition = WienerModel(2, 1.0).transition(Step.START)
    np.testing.assert_array_equal(transition.F, np.eye(3))
    np.testing.assert_array_equal(transition.Q, np.zeros((3, 3)))


def test_transitions_are_read_only() -> None:
    with pytest.raises(ValueError, match="read-only"):
        WienerModel(1, 1.0).transition(Step.PLUS_X).F[0, 0] = 2.0


@pytest.mark.parametrize(("order", "beta"), [(1, 6.0), (1, 12.0), (2, 21.0), (2, 50.0)])
def test_gauss_markov_q_is_psd_above_the_beta_limit(order: int, beta: float) -> None:
    assert_symmetric_psd(gauss_markov_process_noise(order, 1.3, beta))


@pytest.mark.parametrize(("order", "beta"), [(1, 5.0), (1, 1.0), (2, 20.0), (2, 6.0)])
def test_gauss_markov_below_the_beta_limit_is_rejected(order: int, beta: float) -> None:
    with pytest.raises(ValueError, match="not positive semi-definite"):
        gauss_markov_process_noise(order, 1.0, beta)
    with pytest.raises(ValueError, match="beta"):
        GaussMarkovModel(order, 1.0, beta)


def test_gauss_markov_transition_tends_to_the_wiener_one_for_slow_decay() -> None:
    # With beta -> 0 the curvature never decorrelates: eq. 3-33 becomes eq. 3-23.
    np.testing.assert_allclose(gauss_markov_transition(2, 1e-3), taylor_transition(2), atol=1e-3)


def test_observability_matrices_of_appendix_b() -> None:
    H = np.array([[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(
        observability_matrix(taylor_transition(2), H), [[1, 0, 0], [1, 1, 0.5], [1, 2, 2]]
    )
    for order in (0, 1, 2):
        model = WienerModel(order, 1.0)
        F = model.transition(Step.PLUS_X).F
        assert observability_rank(F, model.measurement_matrix) == order + 1


def test_direction_aware_model_is_observable_only_per_partition() -> None:
    # Eq. 3-54 with both steps in F: (F, H) loses rank (thesis section 3-3-5) ...
    H = np.array([[1.0, 0.0, 0.0]])
    assert observability_rank(np.array([[1.0, 1, 1], [0, 1, 0], [0, 0, 1]]), H) == 2
    # ... while each partition (height and the gradient along the step) is observable.
    model = DirectionAwareModel(1e-3)
    for step in MOVES:
        transition = model.transition(step)
        kept = np.flatnonzero(transition.updated)
        assert observability_rank(transition.F[np.ix_(kept, kept)], H[:, kept]) == 2


@pytest.mark.parametrize("model", [WienerModel(0, 0.2), WienerModel(1, 1e-3)], ids=["w0", "w1"])
def test_steady_state_covariance_solves_the_riccati_equation(model) -> None:
    transition = model.transition(Step.PLUS_X)
    H, R = model.measurement_matrix, np.array([[2.25]])
    kf = KalmanFilter(dim_x=model.n_states, dim_z=1)
    kf.P, kf.H, kf.R = model.initial_covariance(10.0), H, R
    for _ in range(400):
        kf.predict(F=transition.F, Q=transition.Q)
        kf.update(np.array([[0.0]]))
    kf.predict(F=transition.F, Q=transition.Q)
    steady_prior = solve_discrete_are(transition.F.T, H.T, transition.Q, R)
    np.testing.assert_allclose(kf.P, steady_prior, rtol=1e-6)
    if model.order == 0:  # the scalar closed form: P = (q + sqrt(q^2 + 4 q R)) / 2
        q = 0.2
        assert kf.P.item() == pytest.approx((q + np.sqrt(q * q + 4 * q * 2.25)) / 2)
