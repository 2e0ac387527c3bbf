"""The EKF on raw metric samples against today's linear fit, on the same samples.

A stage sweeps up through z while the camera streams, from 4 um below a prediction
that is off by N(0, 1 um) (a scan's prior), one metric sample per frame. Today's
reading waits until the running best sample is followed by two lower ones (the peak
bracketed) and fits `find_peak` (a least-squares parabola in log score) to what it
has; the EKF (`focustrack_focus.peak_ekf.stream_peak`) stops once it is sure to
`STOP_SIGMA_UM` and its samples have reached the peak. Both read the same samples:
frames used and the error against the truth.

Sources: curves of the simulator's shape (the curve model's Lorentzian with the width
and background of its normalised variance, 2% score noise, 0.5 um apart), and the
shared real whole-slide curves (`wsi_focus_curves`: 20 fields, BRENNER, 0.5 um a
step, sampled sparsely: every second step, 1 um; the hand label as the truth), their
shape learnt from the other fields (leave one out), as a slide's first tiles teach it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from focustrack_focus.curve_model import fit_curve, lorentzian
from focustrack_focus.peak import find_peak
from focustrack_focus.peak_ekf import stream_peak
from focustrack_focus.real_data import load_wsi_fields

#: The EKF stops when its sigma is below this, um.
STOP_SIGMA_UM = 0.15
#: The simulator's normalised-variance curve: half width (um), background share, noise.
SIM_SHAPE = (2.3, 0.1, 0.02)
#: The real curves' step (um) and metric.
WSI_STEP_UM, WSI_METRIC = 0.5, "BRENNER"


@dataclass(frozen=True)
class StreamScore:
    """One reading over the trials: frames used per tile, mean and largest |error| (um)."""

    frames_per_tile: float
    mae_um: float
    max_error_um: float


def linear_stream(z_um: np.ndarray, scores: np.ndarray) -> tuple[float, int]:
    """Today's reading of a stream: frames until the best is followed by two lower ones,
    then `find_peak` on them; (z um, frames used). Where it reads an edge (no z), the best
    sample's z."""
    best, n = 0, z_um.size
    for i in range(z_um.size):
        if scores[i] > scores[best]:
            best = i
        if i - best >= 2 and i >= 4:
            n = i + 1
            break
    z_peak_um = find_peak(z_um[:n], scores[:n]).z_um
    return (float(z_um[best]) if z_peak_um is None else z_peak_um), n


def _scores(errors: list[float], frames: list[int]) -> StreamScore:
    return StreamScore(
        float(np.mean(frames)), float(np.mean(np.abs(errors))), float(np.max(np.abs(errors)))
    )


def _compare(
    trials: list[tuple[np.ndarray, np.ndarray, float, float, tuple[float, float, float]]],
) -> dict[str, StreamScore]:
    """Both readings of each (z, scores, truth, prior, (gamma, b, noise)) trial."""
    results: dict[str, tuple[list[float], list[int]]] = {"linear fit": ([], []), "ekf": ([], [])}
    for z_um, scores, truth_um, prior_um, (gamma, background, noise) in trials:
        z_linear, n_linear = linear_stream(z_um, scores)
        ekf = stream_peak(
            z_um, scores, mu_um=prior_um, sigma_um=1.5, gamma_um=gamma,
            background=background, noise_share=max(noise, 0.01), stop_sigma_um=STOP_SIGMA_UM,
        )  # fmt: skip
        for name, z, n in (("linear fit", z_linear, n_linear), ("ekf", ekf.z_um, ekf.n_frames)):
            results[name][0].append(z - truth_um)
            results[name][1].append(n)
    return {name: _scores(*lists) for name, lists in results.items()}


def compare(
    seed: int, real_dir: Path, n_sim: int = 200, per_field: int = 10
) -> dict[str, dict[str, StreamScore]]:
    """The comparison on simulator-shaped curves and, where `real_dir` holds them, the real
    whole-slide curves (`real_dir`/wsi_focus_curves)."""
    rng = np.random.default_rng([seed, 21])
    gamma, background, noise = SIM_SHAPE
    trials = []
    for _ in range(n_sim):
        truth_um = rng.uniform(-1.0, 1.0)
        prior_um = truth_um + rng.normal(0.0, 1.0)
        z_um = prior_um - 4.0 + 0.5 * np.arange(25)
        clean = 3.0 * lorentzian(z_um, truth_um, gamma, background)
        trials.append((z_um, clean * (1 + noise * rng.standard_normal(z_um.size)), truth_um,
                       prior_um, SIM_SHAPE))  # fmt: skip
    results = {"simulator shape": _compare(trials)}
    folder = real_dir / "wsi_focus_curves"
    if folder.is_dir() and per_field > 0:
        results[f"real wsi {WSI_METRIC}, 1 um apart"] = _compare(
            _wsi_trials(folder, rng, per_field)
        )
    return results


def _wsi_trials(
    folder: Path, rng: np.random.Generator, per_field: int
) -> list[tuple[np.ndarray, np.ndarray, float, float, tuple[float, float, float]]]:
    fields = load_wsi_fields(folder)
    z_all = [WSI_STEP_UM * np.arange(f.n_positions) for f in fields]
    fits = [
        fit_curve(z, f.scores[WSI_METRIC], WSI_STEP_UM * f.label_index)
        for z, f in zip(z_all, fields, strict=True)
    ]
    trials = []
    for i, (z_full, field) in enumerate(zip(z_all, fields, strict=True)):
        others = [c for j, c in enumerate(fits) if j != i and c is not None]
        shape = (
            float(np.median([c.gamma_um for c in others])),
            float(np.median([c.background for c in others])),
            float(np.median([c.noise_share for c in others])),
        )
        truth_um = WSI_STEP_UM * field.label_index
        for _ in range(per_field):
            prior_um = truth_um + rng.normal(0.0, 1.0)
            start = int(np.clip(round((prior_um - 4.0) / WSI_STEP_UM), 0, field.n_positions - 1))
            index = np.arange(start, field.n_positions, 2)[:25]
            trials.append(
                (z_full[index], field.scores[WSI_METRIC][index], truth_um, prior_um, shape)
            )
    return trials
