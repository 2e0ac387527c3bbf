"""What the doubt between two peaks adds to a measurement's variance (`FocusFlag.MULTI_PEAK`).

The focus service chooses between the peaks of a curve (weighed with the prior it was
sent) and says how sure it is: the chosen peak at z is the focus with chance p
(`Measurement.chosen_probability`), the runner-up at z2 (`Measurement.runner_up_z_um`)
otherwise. The estimator keeps the chosen z (the other peak is never taken: it may be dust
on the coverslip, or a fold's other layer), and counts it with the variance of the focus
about it:

    R = sigma**2 + (1 - p) (z2 - z)**2,

where sigma is the chosen peak's own. Only a runner-up that could be the focus counts: one
within k innovation sigmas of the prior (the z-range policy's k). A peak far outside the
prior (dust 50 um above the section) is no focus this tile could have, and the chosen
peak's own sigma stands. Heights in um, variances in um^2.
"""

from __future__ import annotations

import math

from focustrack_core.domain import FocusFlag, Measurement


def between_peaks_var_um2(
    measurement: Measurement, prior_um: float, innovation_var_um2: float, k_sigma: float
) -> float:
    """The variance (um^2) the runner-up peak adds to `measurement` (0 where it has none, or
    where it lies beyond `k_sigma` sqrt(`innovation_var_um2`) of `prior_um`)."""
    z_um, runner_up_um = measurement.z_um, measurement.runner_up_z_um
    probability = measurement.chosen_probability
    if (
        FocusFlag.MULTI_PEAK not in measurement.flags
        or z_um is None
        or runner_up_um is None
        or probability is None
    ):
        return 0.0
    if abs(runner_up_um - prior_um) > k_sigma * math.sqrt(innovation_var_um2):
        return 0.0
    return (1.0 - probability) * (runner_up_um - z_um) ** 2
