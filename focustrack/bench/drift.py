"""`focustrack bench drift`: focus that moves in time while a slide is scanned.

Scenario `thermal`: generated maps of `--size` x `--size` tiles scanned once while the
instrument warms up (`focustrack_core.drift.ThermalDrift`: settling of `--settle-um`
with time constant `--settle-tau-s`, then a random walk of `--walk-um-per-sqrt-min`,
drawn per map), by `kf-2d-lean` as served (no time state), with the time state
(`focustrack_estimator.time_state`) and with it and revisits.

Scenario `laser`: the same maps and drift, with a reflection autofocus
(`focustrack_core.laser`: the coverslip read with `--laser-noise-um`, the tissue an
offset of 4 +/- 0.4 um from it, smooth over 10 tiles, drawn per map), scanned by
`kf-2d-laser` (a reading per tile, the offset learned, a stack only where the risk rule
asks).

Scenario `second pass`: each map scanned again after its first pass (`kf-2d-lean` with
the time state; its smoothed map is the prior), the slide
moved by `--axial-offset-um` in z and `--lateral-offset-um` in a random direction in x
and y, the walk going on. z: `kf-rescan` with that prior (the drift's offset a random walk,
`RESCAN_PARAMS`), at a stated risk of 0.2% and of 0.05% per tile (`SECOND_PASS`), and
with the scheduler's first-frame check (`CHECKED`: a tile's one frame at its prediction
compared with the first pass's image of it, `--frame-check-ratio`, as `focustrack scan
--first-pass` does; on the simulator's frames of `--check-textures` tiles,
`focustrack.bench.frame_check`).
x, y (`focustrack.bench.lateral_drift`): on the simulator, a virtual tissue slide moved on
the stage by that offset; `--lateral-tiles` tiles of 256 x 256 px imaged before and after
are phase-correlated (`focustrack_scheduler.lateral`, bounded, as the scheduler's
`--first-pass` does) and the stage sent by the offset found: the largest error of the
tiles' placement, where the simulator's stage really went less where the slide lies,
against the first pass's, px (`lateral_error_px`), and without the correction
(`lateral_uncorrected_px`).

Part `ekf` (`focustrack.bench.stream_ekf`): best focus from a stream of raw metric
samples, the focus service's EKF on the curve model against today's linear fit, on the
same samples: frames per tile and error, on simulator-shaped and real curves.

Scans are replayed in
process (`focustrack_estimator.replay`): every acquisition's time is the timing
model's, as the simulator's clock counts it, and a stack sees the map plus the drift
at that time; a tile is scored on its height when it was imaged.

Per scenario and strategy: `in_focus_fraction`, `frames_per_tile`, `time_over_limit`
(scan time over the stage moves plus one frame per tile) and `revisits` per map.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from focustrack.arguments import (
    count_number,
    existing_folder,
    finite_number,
    output_file,
    positive_float,
    seed_number,
    whole_number,
)
from focustrack.bench import frame_check, lateral_drift, stream_ekf
from focustrack.bench import strategies as registry
from focustrack.bench.focus import REAL_DIR
from focustrack.bench.json_report import write_json
from focustrack_core.domain import SlideSettings
from focustrack_core.drift import ThermalDrift
from focustrack_core.geometry import MAX_GRID_SIDE, ScanGrid
from focustrack_core.laser import LaserSpec, coverslip_offsets
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import FAMILIES, add_measurement_noise, family_spec, generate_surfaces
from focustrack_estimator.replay import Replay, ReplayLaser, replay, score
from focustrack_estimator.spatial import RowBankFilter
from focustrack_estimator.strategy import Strategy
from focustrack_scheduler.focus_check import MIN_SHARPNESS_RATIO

#: The time state the benchmark gives a strategy: the walk as simulated, a rate prior of
#: twice the simulated settling's start (2 um / 200 s), and a settling time constant
#: deliberately not the simulator's (300 s against 200 s): the estimator does not know it.
TIME_STATE: dict[str, Any] = {
    "drift_walk_um2_per_s": 0.0015,
    "drift_rate_sigma_um_per_s": 0.02,
    "drift_settle_tau_s": 300.0,
}

#: The strategies of the thermal scenario: label -> (served strategy, parameters).
THERMAL: dict[str, tuple[str, dict[str, Any]]] = {
    "kf-2d-lean": ("kf-2d-lean", {}),
    "kf-2d-lean +time": ("kf-2d-lean", TIME_STATE),
    "kf-2d-lean +time +revisits": ("kf-2d-lean", {**TIME_STATE, "revisit_drift_share": 0.3}),
}

#: The strategies of the laser scenario.
LASER: dict[str, tuple[str, dict[str, Any]]] = {"kf-2d-laser": ("kf-2d-laser", {})}


@dataclass(frozen=True)
class DriftMap:
    """One map of a scenario: its truth and measurements (rows, cols) um, its drift and laser."""

    truth_um: np.ndarray
    measured_um: np.ndarray
    drift: ThermalDrift
    laser: ReplayLaser | None = None


@dataclass(frozen=True)
class DriftScore:
    """One strategy in one scenario, over its maps."""

    in_focus_fraction: float
    frames_per_tile: float
    time_over_limit: float
    revisits: float  # per map
    post_mae_um: float
    # the second pass: the largest placement error over the maps, px, with the stage
    # corrected by the measured offset, and without
    lateral_error_px: float | None = None
    lateral_uncorrected_px: float | None = None


def drift_score(runs: list[Replay], dof_um: float) -> DriftScore:
    s = score(runs, dof_um)
    return DriftScore(
        in_focus_fraction=s.in_focus_fraction,
        frames_per_tile=s.images_per_tile,
        time_over_limit=s.scan_time_s / s.limit_time_s,
        revisits=float(np.mean([r.n_revisits for r in runs])),
        post_mae_um=s.post_mae_um,
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The bench's flags, each typed with the range it takes (`focustrack.arguments`):
    a value out of it is refused before any map is drawn."""
    parser.add_argument("--family", default="standard", choices=sorted(FAMILIES))
    parser.add_argument("--maps", type=count_number, default=4, help="number of maps (default 4)")
    parser.add_argument(
        "--size",
        type=whole_number(2, MAX_GRID_SIDE),
        default=50,
        help="tiles per side, >= 2 (default 50)",
    )
    parser.add_argument("--seed", type=seed_number, default=3000, help="seed (default 3000)")
    parser.add_argument(
        "--noise-um", type=positive_float, default=0.1, help="measurement noise (0.1)"
    )
    parser.add_argument("--dof-um", type=positive_float, default=0.89, help="depth of field (0.89)")
    parser.add_argument(  # the drift may settle up or down
        "--settle-um", type=finite_number(), default=2.0, help="drift settling (2 um)"
    )
    parser.add_argument(
        "--settle-tau-s", type=positive_float, default=200.0, help="settling time constant (200 s)"
    )
    parser.add_argument(
        "--walk-um-per-sqrt-min",
        type=finite_number(0.0),
        default=0.3,
        help="random walk, >= 0 (0.3 um/sqrt min)",
    )
    parser.add_argument(
        "--laser-noise-um",
        type=finite_number(0.0),
        default=0.05,
        help="laser reading noise, >= 0 (0.05 um)",
    )
    parser.add_argument(
        "--axial-offset-um",
        type=finite_number(),
        default=12.0,
        help="second pass: z offset (12 um)",
    )
    parser.add_argument(
        "--lateral-offset-um",
        type=finite_number(0.0),
        default=5.0,
        help="second pass: xy offset, a distance >= 0 in a random direction (5 um)",
    )
    parser.add_argument(
        "--lateral-tiles", type=count_number, default=8, help="second pass: tiles correlated (8)"
    )
    parser.add_argument(
        "--frame-check-ratio",
        type=finite_number(0.0, 1.0, below_high=True),
        default=MIN_SHARPNESS_RATIO,
        help=f"second pass: the first-frame check's least sharpness ratio, in [0, 1) "
        f"({MIN_SHARPNESS_RATIO})",
    )
    parser.add_argument(
        "--check-textures",
        type=count_number,
        default=8,
        help="second pass: the simulator's tiles the first-frame check's frames show (8)",
    )
    parser.add_argument(
        "--ekf-trials",
        type=count_number,
        default=200,
        help="EKF: simulator-shaped streams, and a twentieth of it (at least 1) per real "
        "field (200)",
    )
    # typed only when given: the default folder may be absent, and its rows are then left
    # out, but a folder given by hand that is not there is a mistake
    parser.add_argument(
        "--real-dir",
        type=existing_folder,
        default=REAL_DIR,
        help="EKF: the shared real data's folder",
    )
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the scores as JSON")


def _run_scenario(
    name: str,
    strategies: dict[str, tuple[str, dict[str, Any]]],
    settings: SlideSettings,
    maps: list[DriftMap],
    dof_um: float,
    inspect: Callable[[str, Strategy, Replay], None] | None = None,
) -> dict[str, DriftScore]:
    scores = {}
    for label, (strategy_name, params) in strategies.items():
        runs = []
        for m in maps:
            strategy = registry.create(strategy_name, settings, params)
            run = replay(strategy, m.truth_um, m.measured_um, drift=m.drift, laser=m.laser)
            if inspect is not None:
                inspect(label, strategy, run)
            runs.append(run)
        scores[label] = drift_score(runs, dof_um)
        print(f"  {name}: {label} done", flush=True)
    return scores


def run(args: argparse.Namespace) -> int:
    size = args.size
    grid = ScanGrid(size, size)
    settings = default_settings(grid, dof_um=args.dof_um, noise_sigma_um=args.noise_um)
    truth_um = generate_surfaces(family_spec(args.family, size, size), args.maps, args.seed)
    measured_um = add_measurement_noise(truth_um, args.noise_um, args.seed)
    drifts = [
        ThermalDrift(args.settle_um, args.settle_tau_s, args.walk_um_per_sqrt_min, args.seed + i)
        for i in range(args.maps)
    ]
    maps = [DriftMap(*m) for m in zip(truth_um, measured_um, drifts, strict=True)]
    spec = LaserSpec(noise_um=args.laser_noise_um)
    lasers = [
        ReplayLaser(coverslip_offsets(grid.shape, args.seed + i, spec), spec)
        for i in range(args.maps)
    ]
    laser_maps = [replace(m, laser=laser) for m, laser in zip(maps, lasers, strict=True)]
    traces: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def trace(label: str, strategy: Strategy, run_: Replay) -> None:
        """The first map's true drift and the estimate at each tile, in serpentine order."""
        if label in traces or not isinstance(strategy, RowBankFilter) or strategy.drift is None:
            return
        tile_drift = strategy.tile_drift_um
        order = [(t.row, t.col) for t in grid.serpentine]
        true_um = np.array([run_.truth_um[rc] - maps[0].truth_um[rc] for rc in order])
        traces[label] = (true_um, np.array([tile_drift[rc] for rc in order]))

    title = (
        f"{args.family}: {args.maps} maps of {size}x{size}, seed {args.seed}; noise "
        f"{args.noise_um} um, depth of field {args.dof_um} um; thermal drift: settling "
        f"{args.settle_um} um (tau {args.settle_tau_s:g} s), random walk "
        f"{args.walk_um_per_sqrt_min} um/sqrt(min)"
    )
    print(title, flush=True)
    results = {
        "thermal": _run_scenario("thermal", THERMAL, settings, maps, args.dof_um, trace),
        "laser": _run_scenario("laser", LASER, settings, laser_maps, args.dof_um),
        "second pass": second_pass(args, settings, maps),
    }
    print(format_scores(results))
    streams = stream_ekf.compare(
        args.seed, args.real_dir, n_sim=args.ekf_trials, per_field=max(1, args.ekf_trials // 20)
    )
    print(format_streams(streams))
    if args.json is not None:
        report = {
            "title": title,
            "scenarios": {
                scenario: {label: asdict(s) for label, s in scores.items()}
                for scenario, scores in results.items()
            },
            "ekf": {
                source: {name: asdict(s) for name, s in scores.items()}
                for source, scores in streams.items()
            },
        }
        write_json(args.json, report)
        figure = args.json.with_suffix(".png")
        plot_traces(traces, figure)
        print(f"wrote {args.json} and {figure}")
    return 0


def format_scores(results: dict[str, dict[str, DriftScore]]) -> str:
    """One row per scenario and strategy."""
    header = (
        f"{'scenario, strategy':<40}{'in focus':>10}{'frames/tile':>13}{'time/limit':>12}"
        f"{'revisits':>10}{'post MAE':>10}{'lateral px':>12}{'uncorrected':>13}"
    )
    lines = [header, "-" * len(header)]
    for scenario, scores in results.items():
        for label, s in scores.items():
            lines.append(
                f"{scenario + ': ' + label:<40}{s.in_focus_fraction:>10.2%}"
                f"{s.frames_per_tile:>13.2f}{s.time_over_limit:>12.2f}{s.revisits:>10.1f}"
                f"{s.post_mae_um:>10.3f}"
                + ("" if s.lateral_error_px is None else f"{s.lateral_error_px:>12.2f}")
                + ("" if s.lateral_uncorrected_px is None else f"{s.lateral_uncorrected_px:>13.1f}")
            )
    return "\n".join(lines)


def format_streams(streams: dict[str, dict[str, stream_ekf.StreamScore]]) -> str:
    """One row per source and reading of the EKF comparison."""
    header = f"{'raw samples: source, reading':<48}{'frames':>8}{'MAE um':>9}{'max um':>9}"
    lines = [header, "-" * len(header)]
    for source, scores in streams.items():
        for name, s in scores.items():
            lines.append(
                f"{source + ': ' + name:<48}{s.frames_per_tile:>8.2f}{s.mae_um:>9.3f}"
                f"{s.max_error_um:>9.2f}"
            )
    return "\n".join(lines)


def plot_traces(traces: dict[str, tuple[np.ndarray, np.ndarray]], path: Path) -> None:
    """The first map's true drift against each strategy's estimate, tile by tile."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for i, (label, (true_um, estimate_um)) in enumerate(traces.items()):
        if i == 0:
            ax.plot(true_um, color="black", lw=1.5, label="true drift")
        ax.plot(estimate_um, lw=1, label=f"{label}: estimate")
    ax.set_xlabel("tile (serpentine order)")
    ax.set_ylabel("drift since the scan began, um")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


RESCAN = "kf-rescan"

#: kf-rescan's parameters in the second pass. Its prior map is the first pass's smoothed
#: map, which holds the first pass's drift at each tile: its random walk, frozen along the
#: serpentine, so along the second pass's time too, where this pass's own walk adds to it.
#: So the drift the second pass sees is a random walk of its offset (not of its rate):
#: spectral density this pass's walk (0.0015 um^2/s) plus the first pass's, seen at the
#: second pass's pace (its scan is 1.2 times shorter): 2.2 x 0.0015. An integrated walk
#: (rate noise 1e-4 um^2/s^3, as before) lagged over runs of unmeasured tiles, biased by
#: 0.2-0.3 um over a row: the misses came in neighbours. The slide itself does not change
#: between the passes (no local change: the map's sigma holds its error); a stated risk of
#: 0.2% per tile.
RESCAN_PARAMS: dict[str, Any] = {
    "offset_q_um2_per_s": 2.2 * TIME_STATE["drift_walk_um2_per_s"],
    "local_sigma_um": 0.0,
    "risk_out_of_focus": 0.002,
}

#: The second pass's strategies: the stated risk above, and one of 0.05% per tile (the
#: calibrated tail of 0.2% is a few tiles in 10 000: what a slide of every tile in focus
#: costs).
SECOND_PASS: dict[str, dict[str, Any]] = {
    RESCAN: RESCAN_PARAMS,
    f"{RESCAN} risk 0.05%": {**RESCAN_PARAMS, "risk_out_of_focus": 0.0005},
}

#: The second pass with the scheduler's first-frame check: at the stated risk above, and at
#: a higher one, whose tail the check catches (docs/drift.md).
CHECKED: dict[str, dict[str, Any]] = {
    f"{RESCAN} +check": RESCAN_PARAMS,
    f"{RESCAN} risk 0.5% +check": {**RESCAN_PARAMS, "risk_out_of_focus": 0.005},
}

#: Side of the simulator's tiles correlated for the lateral offset, px.
TILE_PX = 256
#: The side of the simulator's tiles whose frames the first-frame check compares
#: (`frame_check`), px: smaller than a camera's (noisier), rendered in seconds.
CHECK_TILE_PX = 128


@dataclass(frozen=True)
class Offset:
    """A drift moved by `offset_um`: the second pass's axial offset on top of the walk."""

    base: ThermalDrift
    offset_um: float

    def at(self, t_s: float) -> float:
        return self.offset_um + self.base.at(t_s)


def second_pass(
    args: argparse.Namespace, settings: SlideSettings, maps: list[DriftMap]
) -> dict[str, DriftScore]:
    """The second-pass scenario (module docstring): kf-rescan's scores by label
    (`SECOND_PASS`), the first with the largest lateral placement error over the maps,
    corrected and not."""
    runs: dict[str, list[Replay]] = {label: [] for label in [*SECOND_PASS, *CHECKED]}
    placed: list[lateral_drift.Placement] = []
    table = frame_check.sharpness_table(args.seed, args.check_textures, CHECK_TILE_PX)
    for i, m in enumerate(maps):
        first = registry.create("kf-2d-lean", settings, TIME_STATE)
        run_1 = replay(first, m.truth_um, m.measured_um, drift=m.drift)
        smoothed = run_1.focus_map.smoothed_um
        smoothed_sigma = run_1.focus_map.smoothed_sigma_um
        assert smoothed is not None and smoothed_sigma is not None
        prior = {
            "prior_map_um": smoothed.ravel().tolist(),
            "prior_map_sigma_um": smoothed_sigma.ravel().tolist(),
        }
        walk = ThermalDrift(
            walk_um_per_sqrt_min=m.drift.walk_um_per_sqrt_min, seed=m.drift.seed + 100
        )
        drift = Offset(walk, args.axial_offset_um + m.drift.at(run_1.scan_time_s))
        # the first pass's image of a tile: its kept frame, off its truth when imaged by
        reference_dz_um = run_1.focus_map.z_used_um - run_1.truth_um
        for label, params in {**SECOND_PASS, **CHECKED}.items():
            check = None
            if label in CHECKED:
                check = frame_check.SimulatedFrameCheck(
                    table, reference_dz_um, args.frame_check_ratio, args.seed + i
                )
            rescan = registry.create(RESCAN, settings, {**params, **prior})
            runs[label].append(
                replay(rescan, m.truth_um, m.measured_um, drift=drift, frame_check=check)
            )
        # x, y: a virtual slide moved on the simulator's stage, placed again by the stage
        angle = np.random.default_rng([args.seed, i, 17]).uniform(0, 2 * np.pi)
        offset_um = (args.lateral_offset_um * np.cos(angle), args.lateral_offset_um * np.sin(angle))
        placed.append(
            lateral_drift.placement(
                args.seed + i, offset_um, args.lateral_tiles, TILE_PX, 2 * args.lateral_offset_um
            )
        )
        print(f"  second pass: map {i} done", flush=True)
    scores = {label: drift_score(label_runs, args.dof_um) for label, label_runs in runs.items()}
    scores[RESCAN] = replace(
        scores[RESCAN],
        lateral_error_px=max(p.corrected_px for p in placed),
        lateral_uncorrected_px=max(p.uncorrected_px for p in placed),
    )
    return scores
