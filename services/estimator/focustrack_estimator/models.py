"""State-space models of the focus surface along the scan path (thesis chapter 3).

Each model says, for the step that brought the stage onto a tile
(`focustrack_core.geometry.Step`), how the state moves (F), how much it may wander
on the way (Q), and which states a measurement there may correct (the
partitioned update of the direction-aware filter, thesis Algorithm 2). The
measurement is always the height alone, H = [1, 0, ..., 0] (thesis eq. 3-24).

One step is one unit of distance, dx = 1 tile (thesis section 3-3-6: it keeps
the observability matrix well conditioned), so heights are in um, gradients in
um/tile and curvatures in um/tile^2.

Models:
- `WienerModel`: the height's `order`-th derivative is a Wiener process
  (order 0 is Zhang et al.'s random walk); F is the Taylor matrix (eq. 3-23),
  Q the integrated white noise (eq. 3-30). The gradient is taken along the scan
  path, whatever its direction (the thesis' "conventional" filters).
- `GaussMarkovModel`: the highest derivative is a first-order Gauss-Markov
  process (eq. 3-31..3-47); order 1 has a GM gradient, order 2 a GM curvature.
- `DirectionAwareModel`: the thesis' "prior knowledge" filter (eq. 3-54, 3-55):
  x and y gradients as states in fixed slide coordinates, Qx/Qy by step
  direction, and only the height and the gradient along the step updated.

Every model takes `q_height_um2`: white noise entering at the height itself as
well (the thesis' proposed future work, end of section 3-4-2), so an isolated
jump of the surface is absorbed by the height instead of bending the gradient.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from focustrack_core.geometry import Step

#: Signed step length along the scan path, in tiles: -x is a step of -1 in x.
_DX_TILES = {Step.PLUS_X: 1.0, Step.MINUS_X: -1.0, Step.PLUS_Y: 1.0}


@dataclass(frozen=True)
class Transition:
    """One predict step: x' = F x, P' = F P F^T + Q; `updated` masks what the update may change.

    F and Q are (n, n); `updated` is a bool (n,) array (all True except in the
    partitioned update of thesis Algorithm 2, line 15).
    """

    F: np.ndarray
    Q: np.ndarray
    updated: np.ndarray


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only copy: transitions are shared by every filter built on a model."""
    array = np.array(array)
    array.setflags(write=False)
    return array


def taylor_transition(order: int, dx: float = 1.0) -> np.ndarray:
    """F of an `order`-th order Taylor model over a signed step `dx` (thesis eq. 3-23).

    F[i, j] = dx^(j-i) / (j-i)! for j >= i; shape (order + 1, order + 1).
    """
    n = order + 1
    F = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            F[i, j] = dx ** (j - i) / math.factorial(j - i)
    return F


def wiener_process_noise(order: int, q: float, dx: float = 1.0) -> np.ndarray:
    """Q of white noise of spectral density `q` driving the `order`-th derivative (eq. 3-30).

    Q[i, j] = q |dx|^m / (m (n-i)! (n-j)!) with n = order, m = 2n - i - j + 1
    (for order 2 this is eq. 3-30; lower orders are its lower-right blocks).
    A negative step flips the sign of the odd derivatives, hence the factor
    sign(dx)^(i+j): the thesis' sign change of the off-diagonals (Algorithm 2,
    line 6). Shape (order + 1, order + 1), units um^2 (um/tile)^... per entry.
    """
    if order < 0:
        raise ValueError(f"model order must be >= 0, got {order}")
    if q < 0:
        raise ValueError(f"process noise q must not be negative, got {q}")
    n = order
    length, sign = abs(dx), math.copysign(1.0, dx)
    Q = np.empty((n + 1, n + 1))
    for i in range(n + 1):
        for j in range(n + 1):
            m = 2 * n - i - j + 1
            Q[i, j] = (
                sign ** (i + j) * length**m / (m * math.factorial(n - i) * math.factorial(n - j))
            )
    return q * Q


def gauss_markov_transition(order: int, beta_per_tile: float, dx: float = 1.0) -> np.ndarray:
    """F of a height whose `order`-th derivative is Gauss-Markov (thesis eq. 3-33).

    Order 1: [height, gradient]; order 2: [height, gradient, curvature].
    """
    e = math.exp(-beta_per_tile * dx)
    if order == 1:
        return np.array([[1.0, (1.0 - e) / beta_per_tile], [0.0, e]])
    if order == 2:
        return np.array(
            [
                [1.0, dx, (beta_per_tile * dx - 1.0 + e) / beta_per_tile**2],
                [0.0, 1.0, (1.0 - e) / beta_per_tile],
                [0.0, 0.0, e],
            ]
        )
    raise ValueError(f"Gauss-Markov models are of order 1 or 2, got {order}")


def gauss_markov_process_noise(
    order: int, sigma: float, beta_per_tile: float, dx: float = 1.0
) -> np.ndarray:
    """Q of the Gauss-Markov models as the thesis gives it (eq. 3-39..3-47); raises if not PSD.

    `sigma` is the stationary std of the Gauss-Markov state (um/tile for order
    1, um/tile^2 for order 2), 1/`beta_per_tile` its correlation length in
    tiles. Order 2 is eq. 3-47; order 1 is its lower-right 2x2 block (the
    integral of a GM gradient). These closed forms are positive semi-definite
    only for large enough beta (thesis section 3-3-6: beta > 5 and beta > 20;
    with dx = 1 they need beta >= 5.98 and >= 20.99); below, a ValueError.
    """
    if not (sigma > 0 and beta_per_tile > 0):
        raise ValueError(f"sigma and beta must be positive, got {sigma}, {beta_per_tile}")
    b, s2 = beta_per_tile, sigma**2
    e1, e2 = math.exp(-b * dx), math.exp(-2.0 * b * dx)
    q11 = 2 * s2 / b**3 * (dx - b * dx**2 + b**2 * dx**3 / 3 - (1 - e1) / (2 * b) - 2 * dx * e1)
    q12 = 2 * s2 / b**2 * (-dx + b * dx**2 / 2 + dx * e1 + (1 + e2 - 2 * e1) / (2 * b))
    q13 = 2 * s2 / b**2.5 * (-dx * e1 + (1 - e2) / (2 * b))
    q22 = 2 * s2 / b * (dx - 2 / b * (1 - e1) + (1 - e2) / (2 * b))
    q23 = 2 * s2 * ((1 - e1) / b + (1 - e2) / (2 * b))
    q33 = s2 * (1 - e2)
    full = np.array([[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]])
    if order not in (1, 2):
        raise ValueError(f"Gauss-Markov models are of order 1 or 2, got {order}")
    Q = full[1:, 1:] if order == 1 else full
    if np.linalg.eigvalsh(Q).min() < -1e-12 * np.abs(Q).max():
        raise ValueError(
            f"Gauss-Markov order {order} process noise (thesis eq. 3-47) is not positive "
            f"semi-definite at beta = {beta_per_tile} per tile; use beta >= "
            f"{'5.98' if order == 1 else '20.99'} (thesis: beta > {5 if order == 1 else 20})"
        )
    return Q


def height_noise(n_states: int, q_height_um2: float) -> np.ndarray:
    """White noise of variance `q_height_um2` per step entering at the height only, (n, n)."""
    if q_height_um2 < 0:
        raise ValueError(f"q_height_um2 must not be negative, got {q_height_um2}")
    Q = np.zeros((n_states, n_states))
    Q[0, 0] = q_height_um2
    return Q


def observability_matrix(F: np.ndarray, H: np.ndarray) -> np.ndarray:
    """[H; H F; ...; H F^(n-1)] (thesis eq. B-4), shape (n * dim_z, n)."""
    n = F.shape[0]
    blocks, block = [], H
    for _ in range(n):
        blocks.append(block)
        block = block @ F
    return np.vstack(blocks)


def observability_rank(F: np.ndarray, H: np.ndarray) -> int:
    """Rank of the observability matrix: observable iff it equals the state dimension (B-3)."""
    return int(np.linalg.matrix_rank(observability_matrix(F, H)))


class StateSpaceModel(ABC):
    """A linear model of the focus surface along the scan path, with dx = 1 tile."""

    @property
    @abstractmethod
    def state_names(self) -> tuple[str, ...]:
        """The name (with unit) of each state, in order."""

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def measurement_matrix(self) -> np.ndarray:
        """Measurement matrix (1, n): only the height is measured (thesis eq. 3-24)."""
        H = np.zeros((1, self.n_states))
        H[0, 0] = 1.0
        return H

    def transition(self, step: Step) -> Transition:
        """F, Q and the updated-state mask for the move `step` onto a tile (START: no move)."""
        return self._transitions[step]

    @cached_property
    def _transitions(self) -> dict[Step, Transition]:
        n = self.n_states
        table = {Step.START: Transition(np.eye(n), np.zeros((n, n)), np.ones(n, dtype=bool))}
        for step in _DX_TILES:
            F, Q, updated = self._transition(step)
            table[step] = Transition(_frozen(F), _frozen(Q), _frozen(updated))
        return table

    @abstractmethod
    def _transition(self, step: Step) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F, Q and updated-state mask for a real move (not START)."""

    @abstractmethod
    def initial_covariance(self, height_sigma_um: float) -> np.ndarray:
        """P0 (n, n) for a start height known to `height_sigma_um`, derivatives unknown."""


def _derivative_covariance(height_sigma_um: float, derivative_sigmas: list[float]) -> np.ndarray:
    return np.diag(np.square([height_sigma_um, *derivative_sigmas]))


@dataclass(frozen=True)
class WienerModel(StateSpaceModel):
    """The height's `order`-th derivative along the path is a Wiener process (eq. 3-22, 3-23).

    q: spectral density of the white noise driving the highest derivative
    (um^2/tile for order 0, um^2/tile^3 for order 1, um^2/tile^5 for order 2).
    slope_sigma_um_per_tile, curvature_sigma_um_per_tile2: std of the initial
    gradient and curvature (the filter starts at zero for both).
    """

    order: int
    q: float
    q_height_um2: float = 0.0
    slope_sigma_um_per_tile: float = 0.5
    curvature_sigma_um_per_tile2: float = 0.1

    def __post_init__(self) -> None:
        if self.order not in (0, 1, 2):
            raise ValueError(f"Wiener models are of order 0, 1 or 2, got {self.order}")

    @property
    def state_names(self) -> tuple[str, ...]:
        return ("height_um", "gradient_um_per_tile", "curvature_um_per_tile2")[: self.order + 1]

    def _transition(self, step: Step) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Conventional filter: the path is one line, every step dx = +1 along it.
        n = self.order + 1
        Q = wiener_process_noise(self.order, self.q) + height_noise(n, self.q_height_um2)
        return taylor_transition(self.order), Q, np.ones(n, dtype=bool)

    def initial_covariance(self, height_sigma_um: float) -> np.ndarray:
        sigmas = [self.slope_sigma_um_per_tile, self.curvature_sigma_um_per_tile2]
        return _derivative_covariance(height_sigma_um, sigmas[: self.order])


@dataclass(frozen=True)
class GaussMarkovModel(StateSpaceModel):
    """The height's `order`-th derivative is a Gauss-Markov process (eq. 3-31..3-47).

    sigma: stationary std of that derivative (um/tile, or um/tile^2 for order
    2); beta_per_tile: inverse correlation length in tiles. Order 2 also has
    an integrated gradient, started with std `slope_sigma_um_per_tile`.
    """

    order: int
    sigma: float
    beta_per_tile: float
    q_height_um2: float = 0.0
    slope_sigma_um_per_tile: float = 0.5

    def __post_init__(self) -> None:
        # Build Q now so that a beta below the thesis' limit fails at construction.
        gauss_markov_process_noise(self.order, self.sigma, self.beta_per_tile)

    @property
    def state_names(self) -> tuple[str, ...]:
        return ("height_um", "gradient_um_per_tile", "curvature_um_per_tile2")[: self.order + 1]

    def _transition(self, step: Step) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.order + 1
        F = gauss_markov_transition(self.order, self.beta_per_tile)
        Q = gauss_markov_process_noise(self.order, self.sigma, self.beta_per_tile)
        return F, Q + height_noise(n, self.q_height_um2), np.ones(n, dtype=bool)

    def initial_covariance(self, height_sigma_um: float) -> np.ndarray:
        if self.order == 1:
            return _derivative_covariance(height_sigma_um, [self.sigma])
        return _derivative_covariance(height_sigma_um, [self.slope_sigma_um_per_tile, self.sigma])


@dataclass(frozen=True)
class DirectionAwareModel(StateSpaceModel):
    """First-order Wiener model with x and y gradients (thesis eq. 3-54, 3-55, Algorithm 2).

    State [height, dz/dx, dz/dy] in fixed slide coordinates (um, um/tile). A
    step in x moves the height by dx * gradient_x (dx = -1 on right-to-left
    rows) and lets only gradient_x wander (Qx); a step in y likewise with
    gradient_y (Qy). Where `partitioned` (Algorithm 2, line 15), an update
    corrects only the height and the gradient along the last step; otherwise
    every state. q: spectral density of the gradients' white noise (um^2/tile^3).
    """

    q: float
    q_height_um2: float = 0.0
    slope_sigma_um_per_tile: float = 0.5
    partitioned: bool = True

    @property
    def state_names(self) -> tuple[str, ...]:
        return ("height_um", "gradient_x_um_per_tile", "gradient_y_um_per_tile")

    def _transition(self, step: Step) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # The gradient along the step moves the height; the other one is carried over.
        along, other = (1, 2) if step in (Step.PLUS_X, Step.MINUS_X) else (2, 1)
        index = [0, along]
        block_F = taylor_transition(1, _DX_TILES[step])
        block_Q = wiener_process_noise(1, self.q, _DX_TILES[step])
        F, Q = np.eye(3), np.zeros((3, 3))
        F[np.ix_(index, index)] = block_F
        Q[np.ix_(index, index)] = block_Q
        updated = np.ones(3, dtype=bool)
        if self.partitioned:
            updated[other] = False
        return F, Q + height_noise(3, self.q_height_um2), updated

    def initial_covariance(self, height_sigma_um: float) -> np.ndarray:
        slope = self.slope_sigma_um_per_tile
        return _derivative_covariance(height_sigma_um, [slope, slope])
