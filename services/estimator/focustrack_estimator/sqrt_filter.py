"""A square-root Kalman filter: the covariance is carried as a triangular factor, P = S S'.

Why. The covariance form subtracts nearly equal matrices in its update
(P+ = P - K H P, lecture notes eq. 4.77/4.82). With a huge dynamic range in the
state (heights in um next to slopes in um per um when steps are taken in
micrometres, thesis ch. 3 on observability) or a tiny R, round-off makes P
lose symmetry and positive definiteness. Propagating a factor S instead (lecture
notes section 4.4, eq. 4.96-4.97) keeps P = S S' symmetric and positive
semi-definite by construction and halves the dynamic range of the numbers the
filter works with.

How. Both steps are one orthogonal triangularisation (a QR decomposition) of
an array built from the factors, never a subtraction of covariances:

- predict (eq. 4.101-4.108): S S' = F S_ S_' F' + L_Q L_Q' is the Gram
  matrix of the wide array [F S_, L_Q]; a QR of its transpose gives the new
  triangular S directly (the "Delta L_w" update of eq. 4.108 in one step);
- update: the array [[L_R, H S], [0, S]] is triangularised into
  [[X, 0], [Y, Z]] with X X' = H P H' + R (the innovation covariance),
  Y = P H' X^-T (so K = Y X^-1, eq. 4.109/4.120) and Z Z' = P - K H P (the
  posterior, eq. 4.114-4.117). This is the covariance-form counterpart of
  Paige's QR filter (section 4.5, eq. 4.132-4.134), which triangularises the
  information-form array [[S^-1], [L_v C]] instead; the array form needs no
  inverse of S, so a singular prior (a tile whose height is fixed by others) is
  fine.

Q and R may be singular (a Wiener model's Q has rank one): they are factored
with `psd_factor`, which falls back from Cholesky to an eigen-decomposition.

The interface follows FilterPy's `KalmanFilter` so that a strategy can swap
one for the other: attributes x (dim_x, 1), P, F, Q, H, R, y, S (innovation
covariance), K, log_likelihood, and per-step overrides `predict(F=, Q=)` and
`update(z, R=, H=)`; a scalar Q or R means that value times the identity, and
`update(None)` skips a missing measurement. Unlike FilterPy, F may be
rectangular (dim_x_new, dim_x): the state may grow or shrink between steps,
as the 2-D strategies' states do.
"""

from __future__ import annotations

import math

import numpy as np


def psd_factor(A: np.ndarray) -> np.ndarray:
    """A lower-triangular L with L L' = A, for a symmetric positive semi-definite A.

    Cholesky where A is positive definite; otherwise (a rank-deficient Q, or
    round-off making a singular A slightly indefinite) a symmetric square root
    from the eigen-decomposition, negative eigenvalues clipped to zero, brought
    to triangular form by a QR decomposition.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    if A.shape[0] != A.shape[1]:
        raise ValueError(f"a covariance must be square, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise ValueError("covariance contains NaN or infinite entries")
    symmetric = (A + A.T) / 2.0
    try:
        return np.linalg.cholesky(symmetric)
    except np.linalg.LinAlgError:
        eigenvalues, vectors = np.linalg.eigh(symmetric)
        root = vectors * np.sqrt(np.clip(eigenvalues, 0.0, None))  # root @ root.T == A
        return _lower_triangular_root(root)


def _lower_triangular_root(B: np.ndarray) -> np.ndarray:
    """The lower-triangular L (non-negative diagonal) with L L' = B B', for B of shape (n, k)."""
    n = B.shape[0]
    upper: np.ndarray = np.linalg.qr(B.T, mode="r")  # type: ignore[assignment]  # B' = Q U, so B B' = U' U
    L = np.zeros((n, n))
    L[:, : upper.shape[0]] = upper.T[:, :n]
    signs = np.where(np.diag(L) < 0.0, -1.0, 1.0)
    return L * signs  # flipping a column's sign leaves L L' unchanged


def _as_matrix(value: float | np.ndarray, dim: int) -> np.ndarray:
    """A covariance argument as a (dim, dim) matrix; a scalar means value * identity."""
    if np.isscalar(value) or np.ndim(value) == 0:
        return float(value) * np.eye(dim)
    return np.atleast_2d(np.asarray(value, dtype=float))


class SqrtKalmanFilter:
    """A QR-based square-root Kalman filter with FilterPy's KalmanFilter interface.

    Shapes: x (dim_x, 1); P, P_sqrt (dim_x, dim_x); F (dim_x_new, dim_x);
    Q (dim_x_new, dim_x_new); H (dim_z, dim_x); R (dim_z, dim_z); z (dim_z, 1)
    or anything that reshapes to it. Units are the caller's.
    """

    def __init__(self, dim_x: int, dim_z: int) -> None:
        if dim_x < 1 or dim_z < 1:
            raise ValueError(f"dim_x and dim_z must be at least 1, got {dim_x}, {dim_z}")
        self.x = np.zeros((dim_x, 1))
        self.P_sqrt = np.eye(dim_x)  # lower triangular, P = P_sqrt @ P_sqrt.T
        self.F = np.eye(dim_x)
        self.Q = np.eye(dim_x)
        self.H = np.zeros((dim_z, dim_x))
        self.R = np.eye(dim_z)
        self.y = np.zeros((dim_z, 1))  # innovation of the last update
        self.S_sqrt = np.eye(dim_z)  # lower-triangular factor of its covariance
        self.K = np.zeros((dim_x, dim_z))
        self.log_likelihood = 0.0
        self.nis = 0.0  # normalised innovation squared of the last update
        self.x_prior, self.P_sqrt_prior = self.x.copy(), self.P_sqrt.copy()
        self.x_post, self.P_sqrt_post = self.x.copy(), self.P_sqrt.copy()

    @property
    def dim_x(self) -> int:
        return self.x.shape[0]

    @property
    def P(self) -> np.ndarray:  # noqa: N802 (FilterPy's names)
        """The state covariance S S' (symmetric and positive semi-definite by construction)."""
        return self.P_sqrt @ self.P_sqrt.T

    @P.setter
    def P(self, value: np.ndarray) -> None:  # noqa: N802 (FilterPy's names)
        self.P_sqrt = psd_factor(_as_matrix(value, self.dim_x))

    @property
    def P_prior(self) -> np.ndarray:  # noqa: N802 (FilterPy's names)
        return self.P_sqrt_prior @ self.P_sqrt_prior.T

    @property
    def P_post(self) -> np.ndarray:  # noqa: N802 (FilterPy's names)
        return self.P_sqrt_post @ self.P_sqrt_post.T

    @property
    def S(self) -> np.ndarray:  # noqa: N802 (FilterPy's names)
        """Innovation covariance H P H' + R of the last update (FilterPy's name)."""
        return self.S_sqrt @ self.S_sqrt.T

    @property
    def mahalanobis(self) -> float:
        """sqrt(NIS) of the last update, as FilterPy's `mahalanobis`."""
        return math.sqrt(self.nis)

    def predict(
        self,
        F: np.ndarray | None = None,
        Q: float | np.ndarray | None = None,
        *,
        Q_sqrt: np.ndarray | None = None,
    ) -> None:
        """x <- F x; S <- triangular factor of F P F' + Q (lecture notes eq. 4.100-4.108).

        `Q_sqrt` (any L with L L' = Q, not necessarily triangular) may be given
        instead of Q, to skip factoring a Q that is the same at every step.
        """
        F = self.F if F is None else np.atleast_2d(np.asarray(F, dtype=float))
        if Q_sqrt is None:
            Q_sqrt = psd_factor(_as_matrix(self.Q if Q is None else Q, F.shape[0]))
        if F.shape[1] != self.dim_x or Q_sqrt.shape[0] != F.shape[0]:
            raise ValueError(
                f"F {F.shape} and Q {Q_sqrt.shape} do not fit a state of dimension {self.dim_x}"
            )
        self.x = F @ self.x
        # [F S, L_Q] [F S, L_Q]' = F P F' + Q: triangularise the wide array.
        self.P_sqrt = _lower_triangular_root(np.hstack([F @ self.P_sqrt, Q_sqrt]))
        self.x_prior, self.P_sqrt_prior = self.x.copy(), self.P_sqrt.copy()

    def update(
        self,
        z: float | np.ndarray | None,
        R: float | np.ndarray | None = None,
        H: np.ndarray | None = None,
    ) -> None:
        """Correct the state with measurement z (None: no measurement, the prior stands)."""
        if z is None:
            self.y = np.zeros_like(self.y)
            self.x_post, self.P_sqrt_post = self.x.copy(), self.P_sqrt.copy()
            return
        H = self.H if H is None else np.atleast_2d(np.asarray(H, dtype=float))
        dim_z = H.shape[0]
        R = _as_matrix(self.R if R is None else R, dim_z)
        z = np.asarray(z, dtype=float).reshape(dim_z, 1)
        if H.shape[1] != self.dim_x or R.shape != (dim_z, dim_z):
            raise ValueError(
                f"H {H.shape} and R {R.shape} do not fit a state of dimension {self.dim_x}"
            )
        n = self.dim_x
        # Pre-array [[L_R, H S], [0, S]]; its lower-triangular form [[X, 0], [Y, Z]] has
        # X X' = H P H' + R, Y X' = P H', Z Z' = P - P H' (H P H' + R)^-1 H P.
        pre = np.zeros((dim_z + n, dim_z + n))
        pre[:dim_z, :dim_z] = psd_factor(R)
        pre[:dim_z, dim_z:] = H @ self.P_sqrt
        pre[dim_z:, dim_z:] = self.P_sqrt
        post = _lower_triangular_root(pre)
        X, Y, Z = post[:dim_z, :dim_z], post[dim_z:, :dim_z], post[dim_z:, dim_z:]

        self.y = z - H @ self.x
        # X is triangular and tiny (dim_z square): np.linalg.solve is backward stable on it
        # and, unlike scipy's solve_triangular with trans="T", fast.
        whitened = np.linalg.solve(X, self.y)  # X^-1 y
        self.K = np.linalg.solve(X.T, Y.T).T  # Y X^-1
        self.x = self.x + Y @ whitened
        self.P_sqrt = Z
        self.S_sqrt = X
        self.nis = float(np.sum(whitened**2))
        log_det = 2.0 * float(np.sum(np.log(np.abs(np.diag(X)))))
        self.log_likelihood = -0.5 * (dim_z * math.log(2.0 * math.pi) + log_det + self.nis)
        self.x_post, self.P_sqrt_post = self.x.copy(), self.P_sqrt.copy()
