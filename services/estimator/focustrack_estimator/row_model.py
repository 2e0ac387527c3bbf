"""The row model of `kf-2d` and its fixed-interval smoother (docs/spatial.md).

`RowModel` is a separable Gaussian field (Matern-3/2 in x and y) plus a plane, as a
state-space model over rows; `step_rows` applies its row-to-row transition without
forming it; `smooth_member` is the Rauch-Tung-Striebel smoother of one such model over
the rows, column block by column block. `spatial.RowBankFilter` runs a bank of them.
Heights in um, lengths in tiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg

from focustrack_core.domain import SlideSettings
from focustrack_estimator.kalman_strategies import rts_gains

#: State elements of the plane in `RowModel`: offset (um), tilt along x and y (um/tile).
N_PLANE = 3


def matern32(distance: np.ndarray, length: float) -> np.ndarray:
    """Matern-3/2 correlation at `distance` for length scale `length` (same units)."""
    a = math.sqrt(3.0) * np.abs(distance) / length
    return (1.0 + a) * np.exp(-a)


@dataclass(frozen=True)
class RowModel:
    """A separable Gaussian field sigma^2 k(dy) k(dx), Matern-3/2 in both, plus a plane.

    As a state-space model over rows (a strip processor): the state is
    [offset, tilt_x, tilt_y, (f, df/dy) of column 0, (f, df/dy) of column 1, ...]
    (the plane's three coefficients are constant over the slide); from one row
    to the next each column's (f, df/dy) follows the exact discretisation of the
    Matern-3/2 stochastic differential equation (a 2-state Markov process in y),
    with process noise correlated across columns by k(dx). The filter over this
    state is exact Gaussian-process regression for the separable covariance
    plus a plane with a Gaussian prior (universal kriging when that prior is vague).
    """

    sigma_um: float
    length_tiles: float
    tilt_sigma_um_per_tile: float  # prior std of each tilt coefficient
    cols: int

    @cached_property
    def _lam(self) -> float:
        return math.sqrt(3.0) / self.length_tiles

    @cached_property
    def _column_corr(self) -> np.ndarray:
        c = np.arange(self.cols)
        return matern32(c[:, None] - c[None, :], self.length_tiles)

    @cached_property
    def _stationary_y(self) -> np.ndarray:
        """Stationary covariance of (f, df/dy) of one column per unit sigma^2."""
        return np.diag([1.0, self._lam**2])

    @cached_property
    def step_y(self) -> np.ndarray:
        """exp(A) of the Matern-3/2 SDE matrix A = [[0, 1], [-lam^2, -2 lam]] (one row), 2x2."""
        lam = self._lam
        return math.exp(-lam) * np.array([[1.0 + lam, 1.0], [-(lam**2), 1.0 - lam]])

    @cached_property
    def F(self) -> np.ndarray:  # noqa: N802 (the equations' names)
        """Row-to-row transition, (N_PLANE + 2 cols) square."""
        return scipy.linalg.block_diag(np.eye(N_PLANE), np.kron(np.eye(self.cols), self.step_y))

    @cached_property
    def field_noise_per_um2(self) -> np.ndarray:
        """Row-to-row process noise of the field states per unit sigma^2, (2 cols) square.

        Stationary minus propagated covariance of (f, df/dy), correlated across x by k(dx).
        """
        A, P = self.step_y, self._stationary_y
        return np.kron(self._column_corr, P - A @ P @ A.T)

    @cached_property
    def Q(self) -> np.ndarray:  # noqa: N802 (the equations' names)
        """Row-to-row process noise (um^2), (N_PLANE + 2 cols) square; the plane has none."""
        return scipy.linalg.block_diag(
            np.zeros((N_PLANE, N_PLANE)), self.sigma_um**2 * self.field_noise_per_um2
        )

    def initial(self, offset_sigma_um: float) -> np.ndarray:
        """Covariance of the first row's state: the plane and the stationary field."""
        tilt_var = self.tilt_sigma_um_per_tile**2
        plane = np.diag([offset_sigma_um**2, tilt_var, tilt_var])
        field = self.sigma_um**2 * np.kron(self._column_corr, self._stationary_y)
        return scipy.linalg.block_diag(plane, field)


#: Column blocks the smoother runs at once (one batch): their row states, rows x blocks x
#: (N_PLANE + 2 x 32)^2 floats with the default blocks, are what it holds (57 MB at 200 rows).
SMOOTH_BATCH_BLOCKS = 8


def step_rows(M: np.ndarray, step: np.ndarray) -> None:
    """M <- F M in place, F = block_diag(I (N_PLANE), `step` for each column's (f, df/dy)):
    `RowModel.F` applied without forming it.

    `M` (n, N_PLANE + 2 cols, k); `step` (n, 2, 2), one per leading index, or (2, 2).
    Element-wise on the rows of each column's pair: a batch of 2x2 matrix products
    (one per column and member) costs many times more.
    """
    a, b, c, d = (
        np.asarray(step)[..., i, j, None, None] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1))
    )
    f, g = M[:, N_PLANE::2], M[:, N_PLANE + 1 :: 2]
    f_new = a * f + b * g
    g *= d
    g += c * f
    f[...] = f_new


def smooth_member(
    model: RowModel,
    settings: SlideSettings,
    z_um: np.ndarray,
    R_um2: np.ndarray,
    *,
    block_cols: int,
    margin_cols: int,
) -> tuple[np.ndarray, np.ndarray]:
    """One strip model's smoothed heights (um) and variances (um^2) given the measurements.

    `z_um` and `R_um2` (rows reached, cols) hold each measured tile's height and
    variance, NaN where there is none. The model is filtered and RTS-smoothed
    over rows (step k is row k, its posterior the state after the row's
    measurements, which for this model is exactly the Gaussian-process
    posterior) on column blocks: the tiles of each block of `block_cols`
    columns are read from a strip filter over a window of `block_cols` + 2
    `margin_cols` columns around it (shifted inward at the slide's edges, so
    every window has the same width). A block's margins stand in for the
    columns beyond, whose measurements a Matern field a few lengths away barely
    feels; where one window spans the grid the result is the exact smoother.

    The blocks run `SMOOTH_BATCH_BLOCKS` at a time, as one batch (their windows
    have the same model and width), so that memory is rows x
    `SMOOTH_BATCH_BLOCKS` x (N_PLANE + 2 width)^2 floats whatever the slide's
    width: per row one prediction and one batch update with the row's
    measurements (the same as the tile-by-tile updates), and the backward pass
    of Rauch-Tung-Striebel, C_k = P+_k F' (P-_{k+1})^-1, with P-_{k+1} = F P+_k
    F' + Q recomputed instead of stored. A tile without a measurement has a zero
    measurement row (and unit R): it then adds nothing to the update, exactly.
    """
    rows, cols = z_um.shape
    width = min(cols, block_cols + 2 * margin_cols)
    if width == cols:  # one window spans the grid: one block, the exact smoother
        block_cols = cols
    starts = np.arange(0, cols, block_cols)
    los = np.clip(starts - margin_cols, 0, cols - width)  # each window's first column
    window = RowModel(model.sigma_um, model.length_tiles, model.tilt_sigma_um_per_tile, width)
    mean_um, var_um2 = np.full((rows, cols), np.nan), np.full((rows, cols), np.nan)
    for first in range(0, len(starts), SMOOTH_BATCH_BLOCKS):
        batch = slice(first, first + SMOOTH_BATCH_BLOCKS)
        _smooth_windows(
            window, settings, z_um, R_um2, starts[batch], los[batch], block_cols, mean_um, var_um2
        )
    return mean_um, var_um2


def _smooth_windows(
    window: RowModel,
    settings: SlideSettings,
    z_um: np.ndarray,
    R_um2: np.ndarray,
    starts: np.ndarray,
    los: np.ndarray,
    block_cols: int,
    mean_um: np.ndarray,
    var_um2: np.ndarray,
) -> None:
    """`smooth_member` on the blocks starting at columns `starts` (windows from `los`), as one
    batch; writes each block's smoothed heights (um) and variances (um^2) into the maps."""
    rows, cols = z_um.shape
    grid = settings.grid
    width = window.cols
    n_blocks, dim = len(starts), N_PLANE + 2 * width
    columns = los[:, None] + np.arange(width)  # (n_blocks, width) each window's columns
    # Measurement rows of the windows' tiles: the plane at each tile plus its column's field.
    H = np.zeros((n_blocks, width, dim))
    H[:, :, 0] = 1.0
    H[:, :, 1] = columns - (grid.cols - 1) / 2.0
    H[:, np.arange(width), N_PLANE + 2 * np.arange(width)] = 1.0
    Q = window.Q

    def predict(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """F x and F P F' + Q for the batch (copies)."""
        x, P = x.copy(), P.copy()
        step_rows(x[:, :, None], window.step_y)
        step_rows(P, window.step_y)
        step_rows(P.transpose(0, 2, 1), window.step_y)
        return x, P + Q

    def rows_h(r: int) -> np.ndarray:
        H[:, :, 2] = r - (grid.rows - 1) / 2.0
        return H

    x_prior = np.zeros((rows, n_blocks, dim))
    x_post, P_post = np.zeros((rows, n_blocks, dim)), np.zeros((rows, n_blocks, dim, dim))
    x = np.zeros((n_blocks, dim))
    x[:, 0] = settings.start_z_um
    P = np.broadcast_to(window.initial(settings.start_sigma_um), (n_blocks, dim, dim)).copy()
    for r in range(rows):
        if r:
            x, P = predict(x, P)
        x_prior[r] = x
        z, R = z_um[r, columns], R_um2[r, columns]  # (n_blocks, width)
        measured = np.isfinite(z)
        if measured.any():  # the row's tiles at once: the same as one by one
            Hr = rows_h(r) * measured[:, :, None]
            HP = Hr @ P
            S = HP @ Hr.transpose(0, 2, 1)
            S[:, np.arange(width), np.arange(width)] += np.where(measured, R, 1.0)
            L = np.linalg.cholesky(S)
            # np.linalg.solve on the triangular L: scipy's solve_triangular took 18 ms a
            # call here on a loaded 2-core machine, LAPACK's gesv well under one.
            B = np.linalg.solve(L, HP)  # L^-1 H P
            innovation = np.where(measured, z, 0.0) - np.einsum("bwd,bd->bw", Hr, x)
            e = np.linalg.solve(L, innovation[:, :, None])[:, :, 0]
            x = x + np.einsum("bwd,bw->bd", B, e)
            P = P - B.transpose(0, 2, 1) @ B
            P = (P + P.transpose(0, 2, 1)) / 2.0
        x_post[r], P_post[r] = x, P

    # Each block's own columns within its window.
    core = [
        slice(s - lo, min(cols, s + block_cols) - lo) for s, lo in zip(starts, los, strict=True)
    ]

    def read(r: int, xs: np.ndarray, Ps: np.ndarray) -> None:
        Hs = rows_h(r)
        means = np.einsum("bwd,bd->bw", Hs, xs)
        variances = np.sum((Hs @ Ps) * Hs, axis=-1)
        for b, own in enumerate(core):
            mean_um[r, los[b] + own.start : los[b] + own.stop] = means[b, own]
            var_um2[r, los[b] + own.start : los[b] + own.stop] = variances[b, own]

    xs, Ps = x_post[-1], P_post[-1]
    read(rows - 1, xs, Ps)
    for k in range(rows - 2, -1, -1):
        x_next, P_next = predict(x_post[k], P_post[k])  # row k+1's prior
        FP = P_post[k].copy()
        step_rows(FP, window.step_y)  # F P+_k
        C = rts_gains(FP, P_next)  # P+_k F' (P-_{k+1})^-1
        xs = x_post[k] + np.einsum("bij,bj->bi", C, xs - x_next)
        Ps = P_post[k] + C @ (Ps - P_next) @ C.transpose(0, 2, 1)
        read(k, xs, Ps)
