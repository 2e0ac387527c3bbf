"""A kf-rescan prior map leaves the slide's JSON for an .npy file the estimator takes apart."""

from __future__ import annotations

import io

import numpy as np

from focustrack_client import models as api
from focustrack_scheduler.plan import prior_upload


def _rescan(rows: int, cols: int, **params: api.ParamValue) -> api.SlideCreate:
    return api.SlideCreate(strategy="kf-rescan", grid=api.Grid(rows=rows, cols=cols), params=params)


def _array(npy: bytes | None) -> np.ndarray:
    assert npy is not None
    return np.load(io.BytesIO(npy), allow_pickle=False)


def test_a_map_and_its_sigmas_go_as_one_npy_stack_and_leave_the_json() -> None:
    map_um = np.arange(200 * 200, dtype=float).reshape(200, 200) / 1e3
    sigma_um = np.full((200, 200), 0.07)
    config = _rescan(
        200, 200, prior_map_um=map_um.ravel().tolist(), prior_map_sigma_um=sigma_um.ravel().tolist()
    )
    created, npy = prior_upload(config.model_copy(update={"label": "pass 2"}))
    assert api.PRIOR_MAP_PARAM not in created.params
    assert api.PRIOR_SIGMA_PARAM not in created.params
    assert created.label == "pass 2" and created.grid == config.grid
    assert len(created.model_dump_json()) < 64 * 1024  # under the estimator's JSON limit
    stack = _array(npy)
    assert stack.dtype == np.float64 and stack.shape == (2, 200, 200)
    np.testing.assert_array_equal(stack[0], map_um)
    np.testing.assert_array_equal(stack[1], sigma_um)


def test_one_sigma_for_every_tile_stays_a_parameter() -> None:
    created, npy = prior_upload(
        _rescan(2, 3, prior_map_um=[1, 2, 3, 4, 5, 6.5], prior_map_sigma_um=[0.2])
    )
    assert created.params == {api.PRIOR_SIGMA_PARAM: [0.2]}
    np.testing.assert_array_equal(_array(npy), [[1, 2, 3], [4, 5, 6.5]])


def test_without_a_map_or_with_one_that_does_not_fit_the_config_is_sent_as_it_is() -> None:
    for config in (
        _rescan(2, 2),
        _rescan(2, 2, prior_map_um=[]),
        _rescan(2, 2, prior_map_um=[1.0, 2.0, 3.0]),  # the estimator says what is wrong
        api.SlideCreate(strategy="kf-2d", grid=api.Grid(rows=2, cols=2), params={"q": 1.0}),
    ):
        assert prior_upload(config) == (config, None)
