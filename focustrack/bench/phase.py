"""`focustrack bench phase`: the paper's Table 2 on Data Set 1, with two baselines of ours.

On `focustrack_phase.simulate.data_set_1` (100 planes of 100x100 px, 532 nm, 0.5 um
steps over 50 um, gamma = 0.998 photons per pixel, our documented weak object), the
sparse ACEKF (with our phase-frame update, and with the paper's eq. 33 as printed) and
the two baselines of `focustrack_phase.baselines` are scored (ours also anchored to the
slide's empty background, `focustrack_phase.background`, with the same prior) by phase
RMSE (rad, after removing the mean offset), intensity RMSE (relative to the mean
intensity) and time
(median of `--repeats` runs, wall-clock and the process's CPU time `cpu_s`, one core:
scipy.fft with one worker and numpy's element-wise loops are single-threaded). Every
method's regularisation (the filter's prior q0, p0; the baselines' Tikhonov weight) is
chosen per setting from a grid on a training stack of another seed, the same way for
all. Two references frame the figures: "flat field", the
RMSE of a flat estimate, zero phase and unit intensity (the phase's and the intensity's
own spreads: a method is only useful below them), and
"oracle Wiener", the error of the linear weak-object estimate that knows the true
object's power spectrum (for a Gaussian object no estimator from these frames does better
on average): it says how far down this object and photon count allow.

`--sweep` adds the smear weaker and smoothed (OBJECTS: flat, oracle, ours and the
weak-object least squares at the paper's setting), gamma in (1, 10, 100, 1000) on 100
planes and 5..100 planes at the paper's gamma. Five more sections run by default:

- the filter against the Wiener estimate with the same knowledge (`known_spectra`): on
  Data Set 1's object and OBJECTS, the Wiener estimate of amplitude and phase that knows
  their spectra as the filter's diagonal covariances can hold them (realised on the stack
  and expected), and the filter with those spectra as its prior, beside the oracle;
- partial coherence: the same object lit by a disk source (condenser NA 0.05, Abbe's
  method in `focustrack_phase.simulate.partially_coherent_stack`), 50 planes of 1 um,
  100 photons, reconstructed with the coherent model (the paper's) and with the filter's
  coherence envelope, each alone and anchored to the background; the phase RMSE of each
  and the part of it below 0.05 cycles/um (the paper's low-frequency "shadow"), and a
  figure;
- the instrument simulator's own phase stacks (`--specimen phase-cells` and
  `phase-blood`, the default condenser NA 0.2 by Abbe's method with 19 source points,
  through the objective's pupil and the camera: not the filter's model), 32 frames
  0.25-8 um above the tile's true focus on the slides of SIMULATOR_SEEDS (which the
  background anchoring was not tuned on), reconstructed with and without the coherence
  envelope and anchored to the background; the correlation with the true phase after
  removing periods over ~6 um (a Gaussian of 10 pixels), the phase RMSE with its part
  below 0.05 cycles/um, the mean phase on the glass, and a figure;
- a real brightfield z-stack of unstained fission yeast (`--real-dir`, skipped where
  missing): no true phase, so how the phase agrees with itself (even against odd planes,
  above against below focus), its spread and the glass found, and a figure;
- speed and memory on one core: 21 planes of `--speed-size-px` (2048) squared, both
  updates, in wall time and CPU time beside their FFTs' alone, and peak memory
  (`focustrack.bench.phase_speed`); and the background anchoring's CPU time on a field
  of that size (`anchoring_speed`).

`--json OUT` writes the scores and PNGs beside OUT (true phase, each method's phase and
its error; the partial-coherence figure).
"""

from __future__ import annotations

import argparse
import functools
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import fft, ndimage

from focustrack.arguments import count_number, output_file, seed_number, whole_number
from focustrack.bench.focus import REAL_DIR
from focustrack.bench.json_report import write_json
from focustrack.bench.phase_speed import SPEED_PLANES, measure_speed
from focustrack_core.surfaces import SurfaceSpec
from focustrack_focus.real_data import YEAST_FOCUS_PLANE, load_yeast
from focustrack_instrument_sim.instrument import Purpose
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec, slides_from_seed
from focustrack_instrument_sim.phase_specimen import GLASS_PHASE_RAD
from focustrack_instrument_sim.simulator_options import MAX_FRAME_SIDE_PX
from focustrack_phase import acekf, baselines, simulate
from focustrack_phase.acekf import FieldEstimate
from focustrack_phase.background import anchor_to_background
from focustrack_phase.propagation import frequency_sq_per_um2, phase_transfer_power

#: The smallest image side the benchmark takes, px.
MIN_SIDE_PX = 16
COHERENCE_CONDENSER_NA = 0.05
COHERENCE_GAMMA = 100.0
COHERENCE_Z_UM = np.arange(1, 51) * 1.0
SHADOW_BELOW_PER_UM = 0.05
SIMULATOR_OFFSETS_UM = 0.25 * np.arange(1, 33)
SIMULATOR_TILES = (("phase-cells", 512), ("phase-blood", 256))
#: Seeds of the simulator's slides the background anchoring was not tuned on.
SIMULATOR_SEEDS = (1, 3)
#: The real yeast stack's illumination: white light, whose wavelength its source does not
#: give; the middle of the visible (`score_real_yeast`).
YEAST_WAVELENGTH_UM = 0.55
YEAST_PIXEL_UM = 0.1075
HIGH_PASS_SIGMA_PX = 10.0
FILTER_Q0 = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0)
FILTER_P0_RATIO = (0.0, -0.5, -0.9)
FILTER_PRIOR_LENGTH_UM = (0.0, 1.0, 2.0, 4.0)
#: The red-cell smear at weaker peak phases, sharp and smoothed (sigma um): how far down
#: each object lets any method go at the paper's photon count.
OBJECTS = ((0.5, 2.0), (0.2, 0.0), (0.2, 2.0), (0.1, 0.0), (0.1, 2.0))

#: The paper's Table 2 (time s, intensity RMSE, phase RMSE rad) on its own Data Set 1.
PAPER: dict[str, tuple[float, float, float]] = {
    "ACEKF (paper)": (1.3e4, 0.0091, 0.0139),
    "diagonalized CEKF (paper)": (0.30, 0.0079, 0.0166),
    "sparse ACEKF (paper)": (0.40, 0.0071, 0.0143),
}
SWEEP_GAMMAS = (1.0, 10.0, 100.0, 1000.0)
SWEEP_PLANES = (5, 10, 20, 50, 100)
TIE_ALPHAS = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)
TIE_MAX_DZ_UM = (0.0, 2.0, 5.0, 10.0, 20.0)
WOLS_ALPHAS = (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0, 1000.0)

Method = Callable[[simulate.SyntheticStack], FieldEstimate]


def errors(estimate: FieldEstimate, truth: np.ndarray) -> tuple[float, float]:
    """(phase RMSE rad after removing the mean offset, intensity RMSE relative to the mean)."""
    phase_error = np.angle(estimate.field * np.conj(truth))
    phase_error -= phase_error.mean()
    intensity_error = estimate.intensity - np.abs(truth) ** 2
    return float(np.sqrt(np.mean(phase_error**2))), float(np.sqrt(np.mean(intensity_error**2)))


def _args(data: simulate.SyntheticStack) -> tuple[np.ndarray, np.ndarray, float, float]:
    return data.stack_counts, data.z_um, data.wavelength_um, data.pixel_um


def _best_alpha(
    solve: Callable[..., FieldEstimate], alphas: tuple[float, ...], train: simulate.SyntheticStack
) -> float:
    """The Tikhonov weight with the lowest phase RMSE on the training stack."""
    return min(alphas, key=lambda a: errors(solve(*_args(train), alpha=a), train.field)[0])


def _best_tie(train: simulate.SyntheticStack) -> tuple[float, float]:
    """TIE's (alpha, max_dz_um) with the lowest phase RMSE on the training stack."""
    grid = [(a, dz) for a in TIE_ALPHAS for dz in TIE_MAX_DZ_UM]
    return min(
        grid,
        key=lambda g: errors(
            baselines.tie_tikhonov(*_args(train), alpha=g[0], max_dz_um=g[1]), train.field
        )[0],
    )


def _best_prior(
    update: acekf.Update,
    train: simulate.SyntheticStack,
    condenser_na: float = 0.0,
    lengths_um: tuple[float, ...] = (0.0,),
) -> acekf.AcekfOptions:
    """The filter's (q0, p0, prior length) with the lowest phase RMSE on the training stack
    (a prior under which it diverges counts as infinitely wrong); the filter alone, its
    field not anchored to the background (`anchored` adds that to the options found)."""

    def phase_rmse(options: acekf.AcekfOptions) -> float:
        try:
            return errors(acekf.reconstruct(*_args(train), options=options), train.field)[0]
        except acekf.FilterDivergedError:
            return float("inf")

    grid = [
        acekf.AcekfOptions(
            q0=q0,
            p0=ratio * q0,
            update=update,
            condenser_na=condenser_na,
            prior_length_um=length,
            background="none",
        )
        for q0 in FILTER_Q0
        for ratio in FILTER_P0_RATIO
        for length in lengths_um
    ]
    return min(grid, key=phase_rmse)


def oracle_phase_rmse(data: simulate.SyntheticStack) -> float:
    """Phase RMSE (rad) of the linear Wiener estimate that knows the object's power spectrum.

    Per spatial frequency f the planes measure the phase through 2 sin(pi lambda z |f|^2)
    with noise variance 1/gamma (the weak-object transfer of `focustrack_phase.baselines`),
    so with the true power |Phi(f)|^2 as its prior the posterior variance is
    |Phi|^2 / (1 + |Phi|^2 gamma sum_z 4 sin^2(chi)); the amplitude is taken as known.
    """
    phase = np.angle(data.field)
    power = np.abs(fft.fft2(phase - phase.mean(), norm="ortho")) ** 2
    freq_sq = frequency_sq_per_um2(phase.shape, data.pixel_um)
    information = len(data.z_um) * phase_transfer_power(freq_sq, data.z_um, data.wavelength_um)
    posterior = power / (1.0 + power * data.gamma_photons * information)
    return float(np.sqrt(posterior.sum() / phase.size))


def symmetrised(power: np.ndarray) -> np.ndarray:
    """A spectrum (height, width) averaged over each bin's mirrors (+-fy, +-fx): what the
    filter's diagonal covariances can hold (Lemma 1's symmetry, the folded grid)."""
    rows = power + np.roll(power[::-1], 1, axis=0)  # bin -fy of row fy is row (-fy) mod height
    return (rows + np.roll(rows[:, ::-1], 1, axis=1)) / 4


def known_spectra(field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|A|^2 and |Phi|^2 (height, width): the symmetrised unitary power spectra of a
    field's amplitude and phase departures from their means."""

    def power(part: np.ndarray) -> np.ndarray:
        return symmetrised(np.abs(fft.fft2(part - part.mean(), norm="ortho")) ** 2)

    return power(np.abs(field)), power(np.angle(field))


def wiener_known_spectra(data: simulate.SyntheticStack) -> tuple[float, float]:
    """(realised, expected) phase RMSE (rad) of the linear Wiener estimate of amplitude and
    phase that knows their spectra as the filter can hold them (`known_spectra`).

    Per frequency, plane z measures c A + s Phi (c, s = 2 cos, 2 sin of pi lambda z |f|^2,
    noise variance 1/gamma): the 2x2 posterior with the prior diag(|A|^2, |Phi|^2). Unlike
    `oracle_phase_rmse` it does not know the amplitude or each bin's own power, and it is
    run on the stack, so it is what the filter could reach with the same knowledge.
    """
    power_amplitude, power_phase = known_spectra(data.field)
    freq_sq = frequency_sq_per_um2(data.field.shape, data.pixel_um)
    gamma = data.gamma_photons
    tiny = 1e-12  # a bin with no power: a prior of (almost) certain zero
    info_aa = 1.0 / np.maximum(power_amplitude, tiny)
    info_pp = 1.0 / np.maximum(power_phase, tiny)
    info_ap = np.zeros(freq_sq.shape)
    rhs_a = np.zeros(freq_sq.shape, dtype=np.complex128)
    rhs_p = np.zeros(freq_sq.shape, dtype=np.complex128)
    for k, z in enumerate(data.z_um):
        chi = np.pi * data.wavelength_um * z * freq_sq
        c, s = 2.0 * np.cos(chi), 2.0 * np.sin(chi)
        measured = fft.fft2(data.stack_counts[k] / gamma - 1.0, norm="ortho")
        info_aa += gamma * c * c
        info_pp += gamma * s * s
        info_ap += gamma * c * s
        rhs_a += gamma * c * measured
        rhs_p += gamma * s * measured
    det = info_aa * info_pp - info_ap**2
    phase_rad = fft.ifft2((info_aa * rhs_p - info_ap * rhs_a) / det, norm="ortho").real
    error = phase_rad - np.angle(data.field)
    error -= error.mean()
    expected = float(np.sqrt(np.sum(info_aa / det) / det.size))
    return float(np.sqrt(np.mean(error**2))), expected


def filter_known_spectra(data: simulate.SyntheticStack, update: acekf.Update) -> float:
    """Phase RMSE (rad) of the sparse ACEKF whose prior is the object's spectra
    (Q_0 = |A|^2 + |Phi|^2, P_0 = |A|^2 - |Phi|^2, `known_spectra`) instead of a tuned one."""
    power_amplitude, power_phase = known_spectra(data.field)
    height, width = data.field.shape
    quarter = (slice(0, height // 2 + 1), slice(0, width // 2 + 1))
    prior = (
        (power_amplitude + power_phase)[quarter],
        (power_amplitude - power_phase)[quarter],
    )
    options = acekf.AcekfOptions(update=update, background="none")
    return errors(acekf.reconstruct(*_args(data), options=options, prior=prior), data.field)[0]


def score_known_spectra(seed: int, size_px: int) -> list[dict[str, Any]]:
    """Does the filter reach the Wiener estimate with the same knowledge? Per object (Data
    Set 1's and OBJECTS, at the paper's setting): the oracle, the Wiener estimate knowing the
    spectra (realised and expected), the filter with those spectra as its prior (both
    updates)."""
    rows: list[dict[str, Any]] = []
    for peak_rad, smooth_um in ((simulate.WEAK_PEAK_PHASE_RAD, 0.0), *OBJECTS):
        data = simulate.data_set_1(
            seed, simulate.DATA_SET_1_GAMMA, simulate.DATA_SET_1_PLANES, size_px, peak_rad,
            smooth_um,
        )  # fmt: skip
        realised, expected = wiener_known_spectra(data)
        rows.append(
            {"peak_phase_rad": peak_rad, "smooth_um": smooth_um,
             "oracle_rad": oracle_phase_rmse(data), "wiener_known_spectra_rad": realised,
             "wiener_known_spectra_expected_rad": expected,
             "ours_known_spectra_rad": filter_known_spectra(data, "phase_frame"),
             "paper_update_known_spectra_rad": filter_known_spectra(data, "paper")}
        )  # fmt: skip
    return rows


def anchored(options: acekf.AcekfOptions) -> acekf.AcekfOptions:
    """`options` with the field anchored to the background (`focustrack_phase.background`)."""
    return replace(options, background="anchor")


def methods(train: simulate.SyntheticStack) -> dict[str, Method]:
    """The four methods on one setting, each regularised on `train`, and ours anchored to
    the background with the same prior; ours may take a smooth prior, the paper's filter
    keeps its white one."""
    ours = _best_prior("phase_frame", train, lengths_um=FILTER_PRIOR_LENGTH_UM)
    paper = _best_prior("paper", train)
    tie_alpha, tie_dz = _best_tie(train)
    wols_alpha = _best_alpha(baselines.weak_object_least_squares, WOLS_ALPHAS, train)
    return {
        f"sparse ACEKF ours q0={ours.q0:g} p0={ours.p0:g} L={ours.prior_length_um:g}": (
            lambda d: acekf.reconstruct(*_args(d), options=ours)
        ),
        "sparse ACEKF ours + background anchoring": (
            lambda d: acekf.reconstruct(*_args(d), options=anchored(ours))
        ),
        f"sparse ACEKF eq.33 q0={paper.q0:g} p0={paper.p0:g}": lambda d: acekf.reconstruct(
            *_args(d), options=paper
        ),
        f"TIE Tikhonov a={tie_alpha:g} dz<={tie_dz:g}": lambda d: baselines.tie_tikhonov(
            *_args(d), alpha=tie_alpha, max_dz_um=tie_dz
        ),
        f"weak-object LS a={wols_alpha:g}": lambda d: baselines.weak_object_least_squares(
            *_args(d), alpha=wols_alpha
        ),
    }


def score_setting(
    gamma: float, planes: int, seed: int, size_px: int, repeats: int
) -> tuple[list[dict[str, Any]], dict[str, np.ndarray], np.ndarray]:
    """Rows (method, phase/intensity RMSE, time) of one setting, each method's phase, truth."""
    data = simulate.data_set_1(seed, gamma, planes, size_px)
    train = simulate.data_set_1(seed + 1000, gamma, planes, size_px)
    flat = FieldEstimate(np.ones(data.field.shape, dtype=np.complex128), data.gamma_photons)
    rows: list[dict[str, Any]] = []
    phases: dict[str, np.ndarray] = {}
    for name, solve in methods(train).items():
        times_s, cpu_s = [], []
        for _ in range(repeats):
            start, start_cpu = time.perf_counter(), time.process_time()
            estimate = solve(data)
            times_s.append(time.perf_counter() - start)
            cpu_s.append(time.process_time() - start_cpu)
        phase_rmse, intensity_rmse = errors(estimate, data.field)
        rows.append(
            {"method": name, "gamma": gamma, "planes": planes, "phase_rmse_rad": phase_rmse,
             "intensity_rmse": intensity_rmse, "time_s": float(np.median(times_s)),
             "cpu_s": float(np.median(cpu_s))}
        )  # fmt: skip
        phases[name] = estimate.phase_rad
    flat_phase_rad, flat_intensity = errors(flat, data.field)
    rows.append(
        {"method": "flat field (reference)", "gamma": gamma, "planes": planes,
         "phase_rmse_rad": flat_phase_rad, "intensity_rmse": flat_intensity, "time_s": None,
         "cpu_s": None}
    )  # fmt: skip
    rows.append(
        {"method": "oracle Wiener (reference)", "gamma": gamma, "planes": planes,
         "phase_rmse_rad": oracle_phase_rmse(data), "intensity_rmse": None, "time_s": None,
         "cpu_s": None}
    )  # fmt: skip
    return rows, phases, np.angle(data.field)


def score_objects(seed: int, size_px: int) -> list[dict[str, Any]]:
    """Phase RMSE on Data Set 1 with each of OBJECTS: the flat and oracle references, ours
    and the weak-object least squares (each tuned on a training stack of another seed)."""
    rows: list[dict[str, Any]] = []
    for peak_rad, smooth_um in OBJECTS:
        gamma, planes = simulate.DATA_SET_1_GAMMA, simulate.DATA_SET_1_PLANES
        data, train = (
            simulate.data_set_1(s, gamma, planes, size_px, peak_rad, smooth_um)
            for s in (seed, seed + 1000)
        )
        ours = _best_prior("phase_frame", train, lengths_um=FILTER_PRIOR_LENGTH_UM)
        wols_alpha = _best_alpha(baselines.weak_object_least_squares, WOLS_ALPHAS, train)
        flat = FieldEstimate(np.abs(data.field).astype(np.complex128), data.gamma_photons)
        rows.append(
            {"peak_phase_rad": peak_rad, "smooth_um": smooth_um,
             "flat_rad": errors(flat, data.field)[0], "oracle_rad": oracle_phase_rmse(data),
             "ours_rad": errors(acekf.reconstruct(*_args(data), options=ours), data.field)[0],
             "ours_anchored_rad": errors(
                 acekf.reconstruct(*_args(data), options=anchored(ours)), data.field
             )[0],
             "weak_object_ls_rad": errors(
                 baselines.weak_object_least_squares(*_args(data), alpha=wols_alpha), data.field
             )[0]}
        )  # fmt: skip
    return rows


def format_rows(rows: list[dict[str, Any]], with_paper: bool) -> str:
    """A plain-text table; the paper's own figures last when `with_paper`."""
    header = f"{'method':<44} {'gamma':>7} {'planes':>6} {'phase rad':>10} {'intensity':>10}"
    lines = [f"{header} {'time s':>9} {'CPU s':>7}"]
    for r in rows:
        intensity = "" if r["intensity_rmse"] is None else f"{r['intensity_rmse']:.4f}"
        seconds = "" if r["time_s"] is None else f"{r['time_s']:.4f}"
        cpu = "" if r["cpu_s"] is None else f"{r['cpu_s']:.4f}"
        lines.append(
            f"{r['method']:<44} {r['gamma']:>7g} {r['planes']:>6} {r['phase_rmse_rad']:>10.4f} "
            f"{intensity:>10} {seconds:>9} {cpu:>7}"
        )
    if with_paper:
        for name, (seconds_p, intensity_p, phase_p) in PAPER.items():
            lines.append(
                f"{name:<44} {0.998:>7g} {100:>6} {phase_p:>10.4f} {intensity_p:>10.4f} "
                f"{seconds_p:>9.4g}"
            )
    return "\n".join(lines)


def write_figure(
    path: Path, truth: np.ndarray, phases: dict[str, np.ndarray], error_rad: float = 0.3
) -> None:
    """True phase, each method's phase (mean offset removed) and its error, in radians
    (the error's colour scale +-`error_rad`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = truth - truth.mean()
    fig, axes = plt.subplots(2, len(phases) + 1, figsize=(4 * (len(phases) + 1), 7))
    low, high = float(truth.min()), float(truth.max())
    image = axes[0, 0].imshow(truth, cmap="viridis", vmin=low, vmax=high)
    axes[0, 0].set_title("true phase (rad)")
    fig.colorbar(image, ax=axes[0, 0])
    axes[1, 0].axis("off")
    for column, (name, phase) in enumerate(phases.items(), start=1):
        shown = phase - phase.mean()
        image = axes[0, column].imshow(shown, cmap="viridis", vmin=low, vmax=high)
        axes[0, column].set_title(name, fontsize=9)
        fig.colorbar(image, ax=axes[0, column])
        image = axes[1, column].imshow(
            shown - truth, cmap="RdBu_r", vmin=-error_rad, vmax=error_rad
        )
        axes[1, column].set_title("error (rad)", fontsize=9)
        fig.colorbar(image, ax=axes[1, column])
    for axis in axes.flat:
        axis.set_xticks([])
        axis.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def band_rmse(phase_error: np.ndarray, pixel_um: float, below_per_um: float) -> float:
    """RMS (rad) of the part of a phase error image below `below_per_um` cycles/um."""
    spectrum = fft.fft2(phase_error - phase_error.mean(), norm="ortho")
    low = np.sqrt(frequency_sq_per_um2(phase_error.shape, pixel_um)) < below_per_um
    return float(np.sqrt(np.sum(np.abs(spectrum[low]) ** 2) / phase_error.size))


def coherence_stack(seed: int, size_px: int) -> simulate.SyntheticStack:
    """Data Set 1's object lit by a disk source of COHERENCE_CONDENSER_NA (Abbe)."""
    field = simulate.weak_object(size_px, seed)
    wavelength_um, pixel_um = simulate.DATA_SET_1_WAVELENGTH_UM, simulate.DATA_SET_1_PIXEL_UM
    stack = simulate.partially_coherent_stack(
        field, COHERENCE_Z_UM, wavelength_um, pixel_um, COHERENCE_GAMMA,
        COHERENCE_CONDENSER_NA, seed,
    )  # fmt: skip
    return simulate.SyntheticStack(
        field, stack, COHERENCE_Z_UM, wavelength_um, pixel_um, COHERENCE_GAMMA
    )


def score_coherence(
    seed: int, size_px: int
) -> tuple[list[dict[str, Any]], np.ndarray, dict[str, np.ndarray]]:
    """Rows (model, phase RMSE, its low-frequency part), the truth and each model's phase;
    each model's prior chosen on a training stack of another seed, then used as it is and
    anchored to the background."""
    data = coherence_stack(seed, size_px)
    train = coherence_stack(seed + 1000, size_px)
    rows: list[dict[str, Any]] = []
    phases: dict[str, np.ndarray] = {}
    for name, condenser_na in (
        ("coherent model (paper)", 0.0),
        ("coherence envelope (ours)", COHERENCE_CONDENSER_NA),
    ):
        tuned = _best_prior("phase_frame", train, condenser_na)
        for label, options in ((name, tuned), (f"{name} + anchoring", anchored(tuned))):
            estimate = acekf.reconstruct(*_args(data), options=options)
            error = np.angle(estimate.field * np.conj(data.field))
            rows.append(
                {"model": label, "condenser_na": COHERENCE_CONDENSER_NA,
                 "gamma": COHERENCE_GAMMA, "planes": len(COHERENCE_Z_UM), "q0": options.q0,
                 "p0": options.p0, "background": options.background,
                 "phase_rmse_rad": errors(estimate, data.field)[0],
                 "low_frequency_rmse_rad": band_rmse(error, data.pixel_um, SHADOW_BELOW_PER_UM)}
            )  # fmt: skip
            phases[label] = estimate.phase_rad
    return rows, np.angle(data.field), phases


@dataclass(frozen=True)
class SimulatorStack:
    """A PHASE stack of the instrument simulator's tile (0, 0) and its truth.

    photons: float64 (frames, height, width), the green channel's counts less the dark
        counts, times the gain; z_um: each frame's height above the tile's true focus.
    """

    photons: np.ndarray
    z_um: np.ndarray
    wavelength_um: float
    pixel_um: float
    condenser_na: float
    true_phase_rad: np.ndarray


def simulator_phase_stack(
    spec: MicroscopeSpec, offsets_um: np.ndarray = SIMULATOR_OFFSETS_UM, seed: int = 1
) -> SimulatorStack:
    """Tile (0, 0) of a seeded slide, as the phase service reads it from the bus."""
    scope = Microscope(slides_from_seed(seed, 1, SurfaceSpec(2, 3)), spec, seed=seed)
    try:
        truth = scope.true_phase("slide-0", 0, 0)
        z_um = truth.focus_z_um + np.sort(offsets_um)
        step_um = float(np.min(np.diff(z_um))) if len(z_um) > 1 else 1.0
        if not np.allclose(np.diff(z_um), step_um):
            raise ValueError("the offsets must be equally spaced")
        plan = scope.plan(
            "slide-0", 0, 0, float(z_um[0]), step_um, len(z_um),
            purpose=Purpose.PHASE, reference_z_um=truth.focus_z_um,
        )  # fmt: skip
        counts = np.stack([frame[..., 1] for frame in scope.render(plan)]).astype(np.float64)
    finally:
        scope.close()
    imaging = plan.imaging
    return SimulatorStack(
        (counts - imaging.dark_counts) * imaging.photons_per_count,
        plan.z_um - plan.reference_z_um,
        imaging.wavelength_um,
        plan.pixel_size_um,
        imaging.condenser_na,
        truth.phase_rad,
    )


@functools.cache
def simulator_tile(kind: str, size_px: int, seed: int) -> SimulatorStack:
    """`simulator_phase_stack` of a `kind` specimen's size_px^2 tile (kept: it is read
    again)."""
    spec = MicroscopeSpec(height=size_px, width=size_px, max_frames=64, specimen_kind=kind)
    return simulator_phase_stack(spec, seed=seed)


@functools.cache
def simulator_estimate(
    kind: str, size_px: int, seed: int, options: acekf.AcekfOptions
) -> FieldEstimate:
    """`acekf.reconstruct` of `simulator_tile(kind, size_px, seed)` with `options` (kept:
    the speed run anchors the first tile's filtered field again)."""
    data = simulator_tile(kind, size_px, seed)
    return acekf.reconstruct(
        data.photons, data.z_um, data.wavelength_um, data.pixel_um, options=options
    )


def high_pass_correlation(estimate_rad: np.ndarray, truth_rad: np.ndarray) -> float:
    """Correlation of two phase images once periods over ~6 sigma are removed (a Gaussian
    of HIGH_PASS_SIGMA_PX): a through-focus stack pins the lowest frequencies poorly."""

    def high_pass(image: np.ndarray) -> np.ndarray:
        return image - ndimage.gaussian_filter(image, HIGH_PASS_SIGMA_PX, mode="wrap")

    return float(np.corrcoef(high_pass(estimate_rad).ravel(), high_pass(truth_rad).ravel())[0, 1])


def score_simulator() -> tuple[list[dict[str, Any]], np.ndarray, dict[str, np.ndarray]]:
    """Rows (seed, specimen, model: correlation, phase RMSE, its low-frequency part, the
    phase on the glass), and the first tile's truth and phases.

    The background anchoring's settings were chosen on seeds 2 and 4
    (`focustrack_phase.background`); these are seeds it was not tuned on.
    """
    rows: list[dict[str, Any]] = []
    figure_truth = np.zeros((0, 0))
    figure_phases: dict[str, np.ndarray] = {}
    for seed in SIMULATOR_SEEDS:
        for kind, size_px in SIMULATOR_TILES:
            data = simulator_tile(kind, size_px, seed)
            glass = np.abs(data.true_phase_rad) < GLASS_PHASE_RAD
            for model, options in (
                ("coherent model (paper)", acekf.AcekfOptions(background="none")),
                ("coherence envelope (ours)", acekf.AcekfOptions(
                    condenser_na=data.condenser_na, background="none")),
                ("envelope + anchoring (ours)", acekf.AcekfOptions(
                    condenser_na=data.condenser_na, background="anchor")),
            ):  # fmt: skip
                estimate = simulator_estimate(kind, size_px, seed, options)
                error = estimate.phase_rad - data.true_phase_rad
                rows.append(
                    {"seed": seed, "specimen": kind, "model": model,
                     "condenser_na": data.condenser_na, "planes": len(data.z_um),
                     "correlation": high_pass_correlation(
                         estimate.phase_rad, data.true_phase_rad),
                     "phase_rmse_rad": float(np.std(error)),
                     "low_frequency_rmse_rad": band_rmse(
                         error, data.pixel_um, SHADOW_BELOW_PER_UM),
                     "glass_phase_rad": float(np.mean(estimate.phase_rad[glass]))}
                )  # fmt: skip
                if (seed, kind) == (SIMULATOR_SEEDS[0], SIMULATOR_TILES[0][0]):
                    figure_truth, figure_phases[model] = data.true_phase_rad, estimate.phase_rad
    return rows, figure_truth, figure_phases


def anchoring_speed(size_px: int) -> dict[str, Any]:
    """CPU seconds of `anchor_to_background` alone on a size_px^2 field with glass and
    cells (the first simulator tile's filtered field, repeated to size_px), and its peak
    memory on that tile (tracemalloc) in complex64 images of the tile's size."""
    kind, tile_px = SIMULATOR_TILES[0]
    data = simulator_tile(kind, tile_px, SIMULATOR_SEEDS[0])
    options = acekf.AcekfOptions(condenser_na=data.condenser_na, background="none")
    tile = simulator_estimate(kind, tile_px, SIMULATOR_SEEDS[0], options).field
    repeats = -(-size_px // tile.shape[0])
    field = np.tile(tile, (repeats, repeats))[:size_px, :size_px]
    start_cpu = time.process_time()
    anchored_field = anchor_to_background(
        field, data.z_um, data.wavelength_um, data.pixel_um, data.condenser_na
    )
    cpu_s = time.process_time() - start_cpu
    tracemalloc.start()
    anchor_to_background(tile, data.z_um, data.wavelength_um, data.pixel_um, data.condenser_na)
    peak_bytes = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"size_px": size_px, "cpu_s": cpu_s,
            "background_share": float(anchored_field.background.mean()),
            "peak_memory_images": peak_bytes / (8 * tile.size)}  # fmt: skip


def score_real_yeast(real_dir: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The filter (its defaults) on a real brightfield z-stack of unstained fission yeast
    (`yeast_brightfield_zstack` of ../shared/data/real: 34 planes 0.3 um apart, 0.1075 um
    pixels, the source's focus at plane 17, white light taken as YEAST_WAVELENGTH_UM, the
    camera's gain unknown: 1 photon a count). No true phase is known, so the row says how
    the phase agrees with itself: from the even planes against the odd ones (the same
    heights, independent noise), and from the planes above focus against those below (the
    two sides of the weak-object transfer); its spread; and the share taken as glass. The
    images: the focal plane (counts) and the phases."""
    frames, z_um = load_yeast(real_dir / "yeast_brightfield_zstack")
    z_um = z_um - z_um[YEAST_FOCUS_PLANE]
    planes = np.arange(len(z_um))

    def phase_of(chosen: np.ndarray) -> acekf.FieldEstimate:
        return acekf.reconstruct(frames[chosen], z_um[chosen], YEAST_WAVELENGTH_UM, YEAST_PIXEL_UM)

    whole = phase_of(planes)
    parts = {
        "even planes": phase_of(planes[::2]), "odd planes": phase_of(planes[1::2]),
        "above focus": phase_of(planes[z_um >= 0]), "below focus": phase_of(planes[z_um <= 0]),
    }  # fmt: skip

    def agreement(a: str, b: str) -> float:
        return float(np.corrcoef(parts[a].phase_rad.ravel(), parts[b].phase_rad.ravel())[0, 1])

    low, high = np.percentile(whole.phase_rad, [1, 99])
    row = {
        "planes": len(z_um), "z_um": [float(z_um[0]), float(z_um[-1])],
        "wavelength_um": YEAST_WAVELENGTH_UM, "pixel_um": YEAST_PIXEL_UM,
        "even_odd_correlation": agreement("even planes", "odd planes"),
        "above_below_correlation": agreement("above focus", "below focus"),
        "phase_p1_rad": float(low), "phase_p99_rad": float(high),
        "background_share": whole.background_share,
    }  # fmt: skip
    images = {"focal plane (counts)": frames[YEAST_FOCUS_PLANE].astype(np.float64)}
    images["phase, every plane (rad)"] = whole.phase_rad
    images |= {f"phase, {name} (rad)": estimate.phase_rad for name, estimate in parts.items()}
    return row, images


def write_images(path: Path, images: dict[str, np.ndarray]) -> None:
    """The images side by side, each on its own scale with a colour bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(images), figsize=(3.2 * len(images), 3.2))
    for axis, (name, image) in zip(axes, images.items(), strict=True):
        shown = axis.imshow(image, cmap="gray" if "counts" in name else "viridis")
        axis.set_title(name, fontsize=9)
        axis.set_xticks([])
        axis.set_yticks([])
        fig.colorbar(shown, ax=axis, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the scores as JSON")
    parser.add_argument("--sweep", action="store_true", help="also sweep gamma and planes")
    parser.add_argument("--seed", type=seed_number, default=1, help="the object's seed (default 1)")
    image_side_px = whole_number(MIN_SIDE_PX, MAX_FRAME_SIDE_PX)
    parser.add_argument(
        "--size-px",
        type=image_side_px,
        default=simulate.DATA_SET_1_SIZE_PX,
        help=f"image side, >= {MIN_SIDE_PX} (100)",
    )
    parser.add_argument("--repeats", type=count_number, default=5, help="timed runs per method (5)")
    parser.add_argument(
        "--speed-size-px",
        type=image_side_px,
        default=2048,
        help=f"image side of the speed run, >= {MIN_SIDE_PX} (2048)",
    )
    parser.add_argument(
        "--real-dir", type=Path, default=REAL_DIR,
        help="the real data's folder (its yeast z-stack; skipped where missing)",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    print("Data Set 1 (gamma 0.998, 100 planes)...", flush=True)
    rows, phases, truth = score_setting(
        simulate.DATA_SET_1_GAMMA, simulate.DATA_SET_1_PLANES, args.seed, args.size_px,
        args.repeats,
    )  # fmt: skip
    print(format_rows(rows, with_paper=True), flush=True)
    print("the filter against the Wiener estimate with the same knowledge...", flush=True)
    known = score_known_spectra(args.seed, args.size_px)
    print(
        f"  {'peak rad':>8} {'smooth um':>9} {'oracle':>7} {'Wiener':>7} {'expected':>8} "
        f"{'ours':>7} {'eq. 33':>7}"
    )
    for row in known:
        print(
            f"  {row['peak_phase_rad']:>8g} {row['smooth_um']:>9g} {row['oracle_rad']:>7.4f} "
            f"{row['wiener_known_spectra_rad']:>7.4f} "
            f"{row['wiener_known_spectra_expected_rad']:>8.4f} "
            f"{row['ours_known_spectra_rad']:>7.4f} {row['paper_update_known_spectra_rad']:>7.4f}"
        )
    objects: list[dict[str, Any]] = []
    sweep: list[dict[str, Any]] = []
    if args.sweep:
        print("Data Set 1, weaker and smoother objects (gamma 0.998, 100 planes)...", flush=True)
        objects = score_objects(args.seed, args.size_px)
        print(
            f"  {'peak rad':>8} {'smooth um':>9} {'flat':>7} {'oracle':>7} {'ours':>7} "
            f"{'anchored':>8} {'LS':>7}"
        )
        for row in objects:
            print(
                f"  {row['peak_phase_rad']:>8g} {row['smooth_um']:>9g} {row['flat_rad']:>7.4f} "
                f"{row['oracle_rad']:>7.4f} {row['ours_rad']:>7.4f} "
                f"{row['ours_anchored_rad']:>8.4f} {row['weak_object_ls_rad']:>7.4f}"
            )
        settings = [(g, simulate.DATA_SET_1_PLANES) for g in SWEEP_GAMMAS]
        settings += [(simulate.DATA_SET_1_GAMMA, n) for n in SWEEP_PLANES]
        for gamma, planes in settings:
            print(f"sweep: gamma {gamma:g}, {planes} planes...", flush=True)
            sweep += score_setting(gamma, planes, args.seed, args.size_px, 1)[0]
        print(format_rows(sweep, with_paper=False), flush=True)
    print(
        f"partial coherence (condenser NA {COHERENCE_CONDENSER_NA}, {COHERENCE_GAMMA:g} "
        f"photons, {len(COHERENCE_Z_UM)} planes)...",
        flush=True,
    )
    coherence, coherence_truth, coherence_phases = score_coherence(args.seed, args.size_px)
    for row in coherence:
        print(
            f"  {row['model']:<28} phase {row['phase_rmse_rad']:.4f} rad, of which below "
            f"{SHADOW_BELOW_PER_UM} cycles/um {row['low_frequency_rmse_rad']:.4f} rad"
        )
    print("the instrument simulator's phase stacks (condenser NA 0.2)...", flush=True)
    simulator, simulator_truth, simulator_phases = score_simulator()
    for row in simulator:
        print(
            f"  seed {row['seed']} {row['specimen']:<12} {row['model']:<28} correlation "
            f"{row['correlation']:.3f}, phase {row['phase_rmse_rad']:.3f} rad (below "
            f"{SHADOW_BELOW_PER_UM} cycles/um {row['low_frequency_rmse_rad']:.3f}), glass at "
            f"{row['glass_phase_rad']:+.3f} rad"
        )
    yeast: dict[str, Any] | None = None
    yeast_images: dict[str, np.ndarray] = {}
    if (args.real_dir / "yeast_brightfield_zstack").is_dir():
        print("a real brightfield z-stack: unstained fission yeast...", flush=True)
        yeast, yeast_images = score_real_yeast(args.real_dir)
        print(
            f"  {yeast['planes']} planes: phase from the even and the odd planes correlate "
            f"{yeast['even_odd_correlation']:.3f}, from above and below focus "
            f"{yeast['above_below_correlation']:.3f}; phase from {yeast['phase_p1_rad']:.2f} "
            f"to {yeast['phase_p99_rad']:.2f} rad (1st-99th percentiles), "
            f"{yeast['background_share']:.0%} taken as glass"
        )
    else:
        print(f"the real yeast z-stack: skipped ({args.real_dir} has none)", flush=True)
    print(f"speed: {SPEED_PLANES} planes of {args.speed_size_px}^2 on one core...", flush=True)
    speed = measure_speed(args.speed_size_px)
    for row in speed:
        print(
            f"  {row['update']:<12} {row['time_s']:.2f} s ({row['cpu_s']:.2f} s of CPU; its "
            f"FFTs alone {row['fft_cpu_s']:.2f} s), peak memory "
            f"{row['peak_memory_images']:.1f} complex64 images"
        )
    anchoring = anchoring_speed(args.speed_size_px)
    print(
        f"  anchoring to the background: {anchoring['cpu_s']:.2f} s of CPU on "
        f"{args.speed_size_px}^2 ({anchoring['background_share']:.0%} glass), peak memory "
        f"{anchoring['peak_memory_images']:.1f} complex64 images"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        figure = args.json.with_suffix(".png")
        coherence_figure = args.json.with_name(args.json.stem + "-coherence.png")
        simulator_figure = args.json.with_name(args.json.stem + "-simulator.png")
        yeast_figure = args.json.with_name(args.json.stem + "-yeast.png")
        if yeast_images:
            write_images(yeast_figure, yeast_images)
        write_figure(figure, truth, phases)
        write_figure(coherence_figure, coherence_truth, coherence_phases, error_rad=0.15)
        write_figure(simulator_figure, simulator_truth, simulator_phases, error_rad=0.5)
        write_json(
            args.json,
            {"data_set_1": rows, "objects": objects, "known_spectra": known,
             "sweep": sweep, "coherence": coherence,
             "simulator": simulator, "real_yeast": yeast, "speed": speed,
             "anchoring_speed": anchoring,
             "figure": figure.name,
             "coherence_figure": coherence_figure.name,
             "simulator_figure": simulator_figure.name,
             "yeast_figure": yeast_figure.name if yeast_images else None,
             "paper": {name: {"time_s": t, "intensity_rmse": i, "phase_rmse_rad": p}
                       for name, (t, i, p) in PAPER.items()}},
        )  # fmt: skip
        figures = [figure, coherence_figure, simulator_figure]
        if yeast_images:
            figures.append(yeast_figure)
        print(f"wrote {args.json} and its figures {', '.join(map(str, figures))}")
    return 0
