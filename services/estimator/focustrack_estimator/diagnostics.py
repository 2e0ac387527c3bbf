"""Innovation diagnostics: is the filter consistent with what it measured? (thesis section 3-4-3)

A Kalman filter whose model and noise levels fit the data produces
innovations that are zero-mean, white (uncorrelated along the scan) and whose
normalised squares (NIS = innovation^2 / predicted variance) average to 1.
These checks work on the normalised innovations e_k = innovation_k / sqrt(S_k),
so a filter whose predicted variance S_k changes along the scan is judged fairly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special

# scipy.special's distribution functions rather than scipy.stats: the same values, and
# importing scipy.stats costs every estimator process about a second of CPU at start.


def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile: x with P(X <= x) = probability for `dof` degrees of freedom."""
    return float(special.chdtri(dof, 1.0 - probability))


_NORMAL_975 = float(special.ndtri(0.975))  # 1.96: the two-sided 95 % bound of N(0, 1)


@dataclass(frozen=True)
class InnovationDiagnostics:
    """Summary of an innovation sequence of n scalar innovations (in scan order).

    autocorrelation: (max_lag + 1,) sample autocorrelation of the normalised
    innovations at lags 0..max_lag (1 at lag 0). A white sequence keeps every
    lag >= 1 within +/- `autocorrelation_bound` (95%, 1.96 / sqrt(n)) but for
    about 1 in 20; the Ljung-Box statistic pools lags 1..max_lag into one test.
    """

    n: int
    mean_um: float  # mean innovation
    mean_z: float  # mean normalised innovation times sqrt(n): ~N(0, 1) if unbiased
    mean_nis: float  # ~1 for a consistent filter
    nis_interval: tuple[float, float]  # 95% interval of mean_nis for a consistent filter
    autocorrelation: np.ndarray
    autocorrelation_bound: float
    ljung_box_q: float
    ljung_box_p: float  # p-value of "white" (chi-square with max_lag degrees of freedom)

    @property
    def zero_mean(self) -> bool:
        return abs(self.mean_z) <= _NORMAL_975

    @property
    def consistent(self) -> bool:
        """Mean NIS within its 95% chi-square interval: predicted variances fit the data."""
        return self.nis_interval[0] <= self.mean_nis <= self.nis_interval[1]

    @property
    def white(self) -> bool:
        """Ljung-Box whiteness test passes at the 5% level."""
        return self.ljung_box_p > 0.05


def autocorrelation(sequence: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation of a 1-D sequence at lags 0..max_lag, about its mean."""
    centred = sequence - sequence.mean()
    energy = float(centred @ centred)
    if energy == 0.0:
        raise ValueError("autocorrelation of a constant sequence is undefined")
    n = centred.size
    return np.array([centred[: n - lag] @ centred[lag:] / energy for lag in range(max_lag + 1)])


def innovation_diagnostics(
    innovation_um: np.ndarray, variance_um2: np.ndarray, max_lag: int = 20
) -> InnovationDiagnostics:
    """Diagnose innovations (n,) in um with their predicted variances S (n,) in um^2.

    Needs n > max_lag + 1; raises ValueError on mismatched, short or invalid input.
    """
    innovation_um = np.asarray(innovation_um, dtype=float)
    variance_um2 = np.asarray(variance_um2, dtype=float)
    if innovation_um.ndim != 1 or innovation_um.shape != variance_um2.shape:
        raise ValueError(
            f"innovations and variances must be 1-D of one length, got "
            f"{innovation_um.shape} and {variance_um2.shape}"
        )
    if max_lag < 1:
        raise ValueError(f"max_lag must be at least 1, got {max_lag}")
    n = innovation_um.size
    if n <= max_lag + 1:
        raise ValueError(f"need more than {max_lag + 1} innovations for {max_lag} lags, got {n}")
    if not (np.all(np.isfinite(innovation_um)) and np.all(variance_um2 > 0)):
        raise ValueError("innovations must be finite and their variances positive")

    normalised = innovation_um / np.sqrt(variance_um2)
    nis = normalised**2
    rho = autocorrelation(normalised, max_lag)
    lags = np.arange(1, max_lag + 1)
    ljung_box_q = float(n * (n + 2) * np.sum(rho[1:] ** 2 / (n - lags)))
    return InnovationDiagnostics(
        n=n,
        mean_um=float(innovation_um.mean()),
        mean_z=float(normalised.mean() * np.sqrt(n)),
        mean_nis=float(nis.mean()),
        # n * mean NIS is chi-square with n degrees of freedom (one per scalar innovation).
        nis_interval=(chi2_quantile(0.025, n) / n, chi2_quantile(0.975, n) / n),
        autocorrelation=rho,
        autocorrelation_bound=float(_NORMAL_975 / np.sqrt(n)),
        ljung_box_q=ljung_box_q,
        ljung_box_p=float(special.chdtrc(max_lag, ljung_box_q)),
    )


def nis_gate(probability: float) -> float:
    """The NIS a consistent filter's scalar innovation stays below with `probability`.

    The chi-square (one degree of freedom) quantile, for `KalmanStrategy`'s
    `gate_nis`: 0.999 gives 10.8, and one measurement in a thousand is rejected
    wrongly.
    """
    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate probability must be in (0, 1), got {probability}")
    return chi2_quantile(probability, 1)
