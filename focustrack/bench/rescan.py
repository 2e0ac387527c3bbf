"""`focustrack bench rescan`: a slide scanned twice, the second pass learning from the first.

Pass 1 scans generated maps with `--first` (kf-2d by default) while the slide
drifts at `--drift-um-per-s`; pass 2 starts `--gap-s` after pass 1 began, so
the slide has drifted by rate x gap (0.02 um/s for 10 minutes: 12 um), and it
has changed locally by `--local-um` (an independent Gaussian per tile), with
new measurement noise. Pass 2 is scanned by `kf-rescan` with pass 1's smoothed
map as its prior, and, for reference, by the strategies of `--compare`
without one. Scans are replayed in process (`focustrack_estimator.replay`: frames
and times counted as the simulator does); pass 2's drift is unknown to every
strategy (start 0 um, start sigma 10 um).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict

import numpy as np

from focustrack.arguments import (
    count_number,
    finite_number,
    output_file,
    positive_float,
    seed_number,
    whole_number,
)
from focustrack.bench import strategies as registry
from focustrack.bench.accuracy import format_reliability
from focustrack.bench.json_report import write_json
from focustrack_core.geometry import MAX_GRID_SIDE, ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import FAMILIES, add_measurement_noise, family_spec, generate_surfaces
from focustrack_estimator.replay import Drift, Replay, Scores, reliability, replay, score
from focustrack_estimator.rescan import RescanFilter

RESCAN = "kf-rescan"


def prior_map(run: Replay) -> tuple[np.ndarray, np.ndarray]:
    """The map (rows, cols) and sigmas (um) a pass leaves for the next: smoothed where it can."""
    fm = run.focus_map
    if fm.smoothed_um is not None and fm.smoothed_sigma_um is not None:
        return fm.smoothed_um, fm.smoothed_sigma_um
    return fm.posterior_um, fm.posterior_sigma_um


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--family", default="standard", choices=sorted(FAMILIES))
    parser.add_argument("--maps", type=count_number, default=8, help="number of maps (default 8)")
    parser.add_argument(
        "--size",
        type=whole_number(2, MAX_GRID_SIDE),
        default=10,
        help="tiles per side, >= 2 (default 10)",
    )
    parser.add_argument("--seed", type=seed_number, default=1000, help="seed (default 1000)")
    parser.add_argument(
        "--noise-um", type=positive_float, default=0.1, help="measurement noise (0.1)"
    )
    parser.add_argument("--dof-um", type=positive_float, default=0.89, help="depth of field (0.89)")
    parser.add_argument(
        "--gap-s", type=finite_number(0.0), default=600.0, help="pass 2 starts after (600 s)"
    )
    parser.add_argument(
        "--drift-um-per-s",
        type=finite_number(),  # the focus drifts up or down
        default=0.02,
        help="drift rate (0.02)",
    )
    parser.add_argument(
        "--local-um", type=finite_number(0.0), default=0.02, help="local change std (0.02)"
    )
    parser.add_argument("--first", default="kf-2d", help="pass 1's strategy (kf-2d)")
    parser.add_argument(
        "--compare", nargs="*", default=["kf-2d", "kf-2d-lean"], help="pass 2 without a prior"
    )
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the scores as JSON")


def run(args: argparse.Namespace) -> int:
    unknown = [n for n in [args.first, *args.compare] if n not in registry.STRATEGIES]
    if unknown:
        print(f"focustrack bench rescan: error: unknown strategy {unknown}", file=sys.stderr)
        return 2
    size, rate = args.size, args.drift_um_per_s
    grid = ScanGrid(size, size)
    truth_um = generate_surfaces(family_spec(args.family, size, size), args.maps, args.seed)
    measured_1 = add_measurement_noise(truth_um, args.noise_um, args.seed)
    rng = np.random.default_rng([args.seed, 3])
    truth_2 = truth_um + args.local_um * rng.standard_normal(truth_um.shape)
    measured_2 = add_measurement_noise(truth_2, args.noise_um, args.seed + 1)
    settings = default_settings(grid, dof_um=args.dof_um, noise_sigma_um=args.noise_um)

    first = [
        replay(registry.create(args.first, settings), t, m, drift=Drift(0.0, rate))
        for t, m in zip(truth_um, measured_1, strict=True)
    ]
    second: dict[str, list[Replay]] = {}
    for name in args.compare:
        second[name] = [
            replay(registry.create(name, settings), t, m, drift=Drift(rate * args.gap_s, rate))
            for t, m in zip(truth_2, measured_2, strict=True)
        ]
    drift_error_um = []
    second[RESCAN] = []
    for run_1, t, m in zip(first, truth_2, measured_2, strict=True):
        base_um, base_sigma_um = prior_map(run_1)
        params = {
            "prior_map_um": base_um.ravel().tolist(),
            "prior_map_sigma_um": base_sigma_um.ravel().tolist(),
        }
        strategy = registry.create(RESCAN, settings, params)
        assert isinstance(strategy, RescanFilter)
        run_2 = replay(strategy, t, m, drift=Drift(rate * args.gap_s, rate))
        second[RESCAN].append(run_2)
        # Pass 1's map holds pass 1's drift at each tile, so the offset kf-rescan ends with
        # is the drift between the two passes' last tiles (the same tile): both scans' ends.
        expected_um = rate * (args.gap_s + run_2.scan_time_s - run_1.scan_time_s)
        drift_error_um.append(strategy.drift_um - expected_um)

    scores = {f"pass 1 {args.first}": score(first, args.dof_um)}
    scores |= {f"pass 2 {name}": score(runs, args.dof_um) for name, runs in second.items()}
    title = (
        f"{args.family}: {args.maps} maps of {size}x{size}, seed {args.seed}; noise "
        f"{args.noise_um} um, depth of field {args.dof_um} um; drift {rate} um/s, pass 2 "
        f"{args.gap_s:g} s after pass 1 ({rate * args.gap_s:g} um), local change "
        f"{args.local_um} um"
    )
    print(format_scores(title, scores))
    bins = reliability(second[RESCAN], args.dof_um)
    stated = float(registry.parameters(RESCAN)["risk_out_of_focus"])
    print(format_reliability(f"pass 2 {RESCAN}", bins, stated, scores[f"pass 2 {RESCAN}"]))
    print(
        f"{RESCAN}: drift between the passes estimated at the end of pass 2, error mean "
        f"{np.mean(drift_error_um):+.3f} um, max |error| {np.max(np.abs(drift_error_um)):.3f} um"
    )
    if args.json is not None:
        report = {
            "title": title,
            "scores": {name: asdict(s) for name, s in scores.items()},
            "reliability": [asdict(b) for b in bins],
            "drift_error_um": drift_error_um,
        }
        write_json(args.json, report)
        print(f"wrote {args.json}")
    return 0


def format_scores(title: str, scores: dict[str, Scores]) -> str:
    """One row per pass and strategy: frames, time against the limit, in focus, errors."""
    header = (
        f"{'pass, strategy':<26}{'images/tile':>13}{'scan time s':>13}{'/ limit':>9}"
        f"{'in focus':>10}{'post MAE':>10}"
    )
    lines = [title, header, "-" * len(header)]
    for name, s in scores.items():
        lines.append(
            f"{name:<26}{s.images_per_tile:>13.2f}{s.scan_time_s:>13.1f}"
            f"{s.scan_time_s / s.limit_time_s:>9.2f}{s.in_focus_fraction:>10.1%}"
            f"{s.post_mae_um:>10.3f}"
        )
    return "\n".join(lines)
