"""RTS smoothing of the 1-D filters: the smoothed layers of the focus map."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, rts_smoother

from focustrack_core.domain import Measurement
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.kalman_strategies import STRATEGIES, rts_gains, rts_smooth
from focustrack_estimator.replay import replay


def test_rts_smooth_equals_filterpys_smoother() -> None:
    rng = np.random.default_rng(0)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]]) * 0.01
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.Q, kf.H, kf.R = F, Q, np.array([[1.0, 0.0]]), np.array([[0.5]])
    kf.P = np.eye(2) * 4.0
    zs = np.cumsum(rng.normal(0.1, 0.3, 40)) + rng.normal(0.0, 0.7, 40)
    x_prior, P_prior, x_post, P_post = [], [], [], []
    for k, z in enumerate(zs):
        if k:
            kf.predict()
        x_prior.append(kf.x[:, 0].copy())
        P_prior.append(kf.P.copy())
        kf.update(np.array([[z]]))
        x_post.append(kf.x[:, 0].copy())
        P_post.append(kf.P.copy())
    Fs = np.array([F] * len(zs))
    xs, Ps = rts_smooth(*map(np.array, (x_prior, P_prior, x_post, P_post)), Fs)
    expected_x, expected_P, _, _ = rts_smoother(
        np.array(x_post)[..., None], np.array(P_post), Fs, np.array([Q] * len(zs))
    )
    np.testing.assert_allclose(xs, expected_x[..., 0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Ps, expected_P, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_smoothed_map_beats_the_filtered_one(name: str) -> None:
    truths = generate_surfaces(SurfaceSpec(rows=12, cols=12), 3, seed=11)
    rng = np.random.default_rng(11)
    filtered, smoothed = [], []
    for truth in truths:
        strategy = registry.create(name, default_settings(ScanGrid(12, 12)))
        fm = replay(strategy, truth, truth + rng.normal(0.0, 1.5, truth.shape)).focus_map
        assert np.all(fm.smoothed_sigma_um <= fm.posterior_sigma_um + 1e-9)
        last = strategy.grid.serpentine[-1]  # smoothing ends where the filter ends
        assert fm.smoothed_um[last.row, last.col] == pytest.approx(
            fm.posterior_um[last.row, last.col]
        )
        filtered.append(np.abs(fm.posterior_um - truth).mean())
        smoothed.append(np.abs(fm.smoothed_um - truth).mean())
    assert np.mean(smoothed) < 0.95 * np.mean(filtered)


def test_smoothed_layers_cover_the_tiles_finished_so_far() -> None:
    strategy = registry.create("kf-wiener0", default_settings(ScanGrid(3, 4)))
    assert strategy.focus_map().smoothed_um is None  # nothing finished yet
    for z_um in (1.0, 2.0, 0.5):
        strategy.record(strategy.next_acquisition(), Measurement(z_um=z_um))
    mid = strategy.focus_map()
    assert np.isfinite(mid.smoothed_um[0, :3]).all() and np.isnan(mid.smoothed_um[0, 3])
    assert np.isnan(mid.smoothed_um[1:]).all()
    # The first tile's smoothed height learns from the later measurements; the last does not.
    assert mid.smoothed_um[0, 0] > mid.posterior_um[0, 0]
    assert mid.smoothed_um[0, 2] == pytest.approx(mid.posterior_um[0, 2])


@pytest.mark.parametrize(
    "params",
    [
        {"drift_walk_um2_per_s": 0.0015},
        {"drift_rate_sigma_um_per_s": 0.001},
        {"drift_rate_q_um2_per_s3": 1e-6},
    ],
    ids=["drift walk alone", "drift rate alone", "rate walk alone"],
)
@pytest.mark.parametrize("name", ["kf-wiener1", "kf-gm2"])
def test_a_drift_state_that_never_varies_leaves_the_smoother_finite(
    name: str, params: dict[str, float]
) -> None:
    """One drift component at zero variance left P- singular: "Singular matrix" at the
    trial scan, for the drift settings docs/drift.md recommends."""
    truth = generate_surfaces(SurfaceSpec(rows=8, cols=8), 1, seed=3)[0]
    strategy = registry.create(name, default_settings(ScanGrid(8, 8)), params)
    noise = np.random.default_rng(3).normal(0.0, 0.5, truth.shape)
    fm = replay(strategy, truth, truth + noise).focus_map
    assert np.isfinite(fm.smoothed_um).all() and np.isfinite(fm.smoothed_sigma_um).all()
    assert np.abs(fm.smoothed_um - truth).mean() < np.abs(fm.posterior_um - truth).mean()


def test_rts_gains_of_a_singular_prior_take_its_pseudo_inverse() -> None:
    P_next = np.array([[[2.0, 0.0], [0.0, 0.0]]])  # the second state never varies
    FP = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    np.testing.assert_allclose(rts_gains(FP, P_next), [[[0.5, 0.0], [0.0, 0.0]]])
