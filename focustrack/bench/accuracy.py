"""`focustrack bench accuracy`: replay focus maps through every strategy and compare them.

Every strategy scans the same maps in serpentine order and sees the same
measurements (`focustrack_estimator.replay`). Per strategy it reports the prior and
posterior mean absolute error and std against the truth, images per tile,
simulated scan time per map (`focustrack_core.timing`, docs/timing.md) and the
in-focus fraction (|z used - truth| <= depth of field / 2).

Maps are generated (`--maps N --size 20 --seed S`, one block per `--family`)
or a user's own (`--truth-map FILE` with `--measured-map FILE`, or with noise
simulated from `--noise-um` and `--seed`). Strategies run with the registry's
defaults, which were chosen on training seeds, never on the maps reported here.

The scan of a generated map starts at 0 um, the mean of the generator (what a
scanner knows of a slide family). A user's map may sit at any absolute height,
so its scan starts at the measured focus of its first tile, as a scanner
focuses once when a slide is loaded.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from focustrack.arguments import (
    count_number,
    output_file,
    output_folder,
    positive_float,
    seed_number,
    whole_number,
)
from focustrack.bench import strategies as registry
from focustrack.bench.json_report import write_json
from focustrack_core.geometry import MAX_GRID_SIDE, ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import (
    FAMILIES,
    OUTLIERS,
    SurfaceSpec,
    add_measurement_noise,
    add_outliers,
    family_spec,
    generate_surfaces,
    load_map,
)
from focustrack_estimator.replay import Replay, RiskBin, Scores, reliability, replay, score

DEFAULT_FAMILY = "standard"

#: The Bayes-optimal reference (when registered): given the family's SurfaceSpec as its
#: parameters, and every strategy's MAE is also printed as a ratio to its MAE.
ORACLE = "gp-oracle"

#: Strategies replayed by another benchmark, by default not here: those that re-scan a
#: slide with the last pass's map (`focustrack bench rescan`; without a map they only track
#: a drift), and those that fuse a reflection autofocus's readings (`focustrack bench
#: drift`; these maps have no laser).
ELSEWHERE = frozenset({"kf-rescan", "kf-2d-laser"})

#: Suffix of the rows scored on a strategy's RTS-smoothed final map.
SMOOTHED_SUFFIX = "-rts"


@dataclass(frozen=True)
class MapSet:
    """Maps replayed together and reported as one block; heights (n_maps, rows, cols) in um."""

    name: str  # a family name, or "user" for a user's maps (also names the plot files)
    title: str  # the block's heading
    truth_um: np.ndarray
    measured_um: np.ndarray
    start_z_um: np.ndarray  # (n_maps,): where each map's scan starts
    spec: SurfaceSpec | None = None  # the generator's spec (None for a user's maps)

    @property
    def n_maps(self) -> int:
        return self.truth_um.shape[0]


def generated_map_sets(
    families: list[str], n_maps: int, size: int, seed: int, noise_um: float
) -> list[MapSet]:
    """One `MapSet` per family of `n_maps` generated size x size maps."""
    sets = []
    for family in families:
        truth_um = generate_surfaces(family_spec(family, size, size), n_maps, seed)
        measured_um = add_measurement_noise(truth_um, noise_um, seed)
        if family in OUTLIERS:
            measured_um = add_outliers(measured_um, OUTLIERS[family], seed)
        sets.append(
            MapSet(
                name=family,
                title=f"{family}: {n_maps} maps of {size}x{size}, seed {seed}",
                truth_um=truth_um,
                measured_um=measured_um,
                start_z_um=np.zeros(n_maps),
                spec=family_spec(family, size, size),
            )
        )
    return sets


def user_map_set(
    truth_path: Path, measured_path: Path | None, noise_um: float, seed: int
) -> MapSet:
    """A user's truth map(s), with measured map(s) given or simulated; raises ValueError."""
    truth_um = _as_stack(load_map(truth_path))
    if measured_path is not None:
        measured_um = _as_stack(load_map(measured_path))
        if measured_um.shape != truth_um.shape:
            raise ValueError(
                f"measured map {measured_path} has shape {measured_um.shape}, "
                f"truth map {truth_path} has {truth_um.shape}"
            )
        source = f"measured {measured_path}"
    else:
        measured_um = add_measurement_noise(truth_um, noise_um, seed)
        source = f"noise simulated, seed {seed}"
    n_maps, rows, cols = truth_um.shape
    first = ScanGrid(rows, cols).serpentine[0]
    return MapSet(
        name="user",
        title=f"{truth_path}: {n_maps} map(s) of {rows}x{cols}, {source}",
        truth_um=truth_um,
        measured_um=measured_um,
        start_z_um=measured_um[:, first.row, first.col],
    )


def _as_stack(maps_um: np.ndarray) -> np.ndarray:
    return maps_um[None] if maps_um.ndim == 2 else maps_um


def replay_all(
    map_sets: list[MapSet],
    names: list[str],
    noise_um: float,
    dof_um: float,
    *,
    progress: bool = True,
) -> dict[str, dict[str, list[Replay]]]:
    """Replays by map set, then by strategy name, each a list over the set's maps."""
    results: dict[str, dict[str, list[Replay]]] = {}
    total = len(names) * sum(map_set.n_maps for map_set in map_sets)
    with tqdm(total=total, desc="replaying", unit="scan", disable=not progress) as bar:
        for map_set in map_sets:
            grid = ScanGrid(*map_set.truth_um.shape[1:])
            by_name: dict[str, list[Replay]] = {}
            for name in names:
                bar.set_postfix_str(f"{map_set.name} {name}")
                params = asdict(map_set.spec) if name == ORACLE and map_set.spec else None
                by_name[name] = []
                for truth_um, measured_um, start_z_um in zip(
                    map_set.truth_um, map_set.measured_um, map_set.start_z_um, strict=True
                ):
                    settings = default_settings(
                        grid,
                        start_z_um=float(start_z_um),
                        dof_um=dof_um,
                        noise_sigma_um=noise_um,
                    )
                    by_name[name].append(
                        replay(registry.create(name, settings, params), truth_um, measured_um)
                    )
                    bar.update()
            results[map_set.name] = by_name
    return results


def score_with_smoothed(replays: dict[str, list[Replay]], dof_um: float) -> dict[str, Scores]:
    """Scores by strategy name, plus a row NAME-rts for every strategy whose maps are smoothed.

    The -rts row is scored on the RTS-smoothed final map in place of the
    posterior; its prior, cost and in-focus fraction are the strategy's own
    (the scan is the same; smoothing only improves the map afterwards).
    """
    scores = {}
    for name, runs in replays.items():
        scores[name] = score(runs, dof_um)
        smoothed_maps = [run.focus_map.smoothed_um for run in runs]
        if runs and all(layer is not None for layer in smoothed_maps):
            smoothed = [
                replace(run, focus_map=replace(run.focus_map, posterior_um=layer))
                for run, layer in zip(runs, smoothed_maps, strict=True)
                if layer is not None
            ]
            scores[name + SMOOTHED_SUFFIX] = score(smoothed, dof_um)
    return scores


def format_table(title: str, scores: dict[str, Scores]) -> str:
    """A table of the scores, one strategy a row, errors in um (a dash where no prior).

    With the oracle among the scores, two more columns give each MAE as a
    ratio to the oracle's; footnotes say what the -rts rows are.
    """

    def number(value: float | None, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    def ratio(value: float | None, reference: float | None) -> str:
        return "-" if value is None or not reference else f"{value / reference:.2f}"

    oracle = scores.get(ORACLE)
    header = (
        f"{'strategy':<20}{'prior MAE':>10}{'prior std':>10}{'post MAE':>10}{'post std':>10}"
        f"{'images/tile':>13}{'scan time s':>13}{'/ limit':>9}{'in focus':>10}"
        + (f"{'prior/oracle':>14}{'post/oracle':>13}" if oracle else "")
    )
    lines = [title, header, "-" * len(header)]
    for name, s in scores.items():
        line = (
            f"{name:<20}{number(s.prior_mae_um, 3):>10}{number(s.prior_std_um, 3):>10}"
            f"{s.post_mae_um:>10.3f}{s.post_std_um:>10.3f}{s.images_per_tile:>13.2f}"
            f"{s.scan_time_s:>13.1f}{s.scan_time_s / s.limit_time_s:>9.2f}"
            f"{s.in_focus_fraction:>10.1%}"
        )
        if oracle:
            line += (
                f"{ratio(s.prior_mae_um, oracle.prior_mae_um):>14}"
                f"{ratio(s.post_mae_um, oracle.post_mae_um):>13}"
            )
        lines.append(line)
    if any(name.endswith(SMOOTHED_SUFFIX) for name in scores):
        lines.append(
            f"NAME{SMOOTHED_SUFFIX}: post MAE/std of NAME's RTS-smoothed final map; its prior, "
            "cost and in-focus fraction are NAME's (the same scan)."
        )
    lines.append(
        "/ limit: scan time over the physical limit (stage moves plus one frame per tile)."
    )
    if oracle:
        lines.append(
            f"{ORACLE}: Bayes-optimal, knows the generator's covariance (no scanner can run it); "
            "ratios are MAE / its MAE."
        )
    return "\n".join(lines)


def stated_risk(name: str) -> float:
    """The out-of-focus risk strategy `name` states by default (0: it states none)."""
    return float(registry.parameters(name).get("risk_out_of_focus", 0.0) or 0.0)


def format_reliability(
    name: str, bins: list[RiskBin], stated: float, scores: Scores, floor: float | None = None
) -> str:
    """The reliability table of one strategy: predicted risk against the achieved rate, and
    the frames its tiles kept (`scores`; several where one is too unsure: `lean.kept_planes`).

    `floor`: the out-of-focus share of the Bayes-optimal oracle on the same maps, one frame
    per tile, where it ran; a stated risk below it is out of reach with one frame per tile
    (for any estimator, where the maps are Gaussian), and the table says so.
    """
    n_tiles = sum(b.n_tiles for b in bins)
    predicted = sum(b.predicted * b.n_tiles for b in bins) / max(n_tiles, 1)
    achieved = sum(b.achieved * b.n_tiles for b in bins) / max(n_tiles, 1)
    lines = [
        f"{name}: stated risk {stated:.1%}; over {n_tiles} tiles predicted {predicted:.2%}, "
        f"achieved {achieved:.2%} out of focus",
        f"  {'predicted risk':<16}{'tiles':>8}{'predicted':>11}{'achieved':>10}",
    ]
    for b in bins:
        band = f"[{b.low:g}, {b.high:g})"
        lines.append(f"  {band:<16}{b.n_tiles:>8}{b.predicted:>11.2%}{b.achieved:>10.2%}")
    lines.append(
        f"  frames kept per tile: {scores.frames_kept_per_tile:.2f} (more than one where one is "
        "too unsure: a tile is in focus when one of its frames is)"
    )
    if floor is not None and floor > stated:
        lines.append(
            f"  one frame per tile could not meet the stated {stated:.1%} here: {ORACLE} (the "
            f"Bayes-optimal filter for these maps' covariance) leaves {floor:.1%} of tiles out "
            "of focus"
        )
    return "\n".join(lines)


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name)


def write_plots(
    directory: Path,
    map_set: MapSet,
    replays: dict[str, list[Replay]],
    scores: dict[str, Scores],
) -> list[Path]:
    """Error heat maps and a summary bar plot of one map set, as PNGs; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    names = list(replays)

    # Mean |posterior - truth| of every tile over the set's maps, one panel per strategy.
    errors = {
        name: np.mean([np.abs(r.focus_map.posterior_um - r.truth_um) for r in runs], axis=0)
        for name, runs in replays.items()
    }
    vmax = float(np.percentile(np.concatenate([e.ravel() for e in errors.values()]), 99))
    n_cols = min(4, len(names))
    n_rows = -(-len(names) // n_cols)
    fig, axes = plt.subplots(
        n_rows, n_cols, figsize=(3.2 * n_cols, 3.0 * n_rows), squeeze=False, layout="constrained"
    )
    for ax in axes.flat[len(names) :]:
        ax.set_axis_off()
    for ax, name in zip(axes.flat, names, strict=False):
        image = ax.imshow(errors[name], cmap="magma", vmin=0.0, vmax=vmax, origin="upper")
        ax.set_title(f"{name}\nMAE {scores[name].post_mae_um:.2f} um", fontsize=9)
        ax.set_xlabel("col (x)")
        ax.set_ylabel("row (y)")
    fig.colorbar(image, ax=axes, label="mean |posterior - truth| (um)", shrink=0.8)
    fig.suptitle(f"Posterior error per tile: {map_set.title}", fontsize=10)
    heat_path = directory / f"errors_{_slug(map_set.name)}.png"
    fig.savefig(heat_path, dpi=110)
    plt.close(fig)

    # Accuracy and cost side by side.
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), layout="constrained")
    x = np.arange(len(names))
    prior = [np.nan if scores[n].prior_mae_um is None else scores[n].prior_mae_um for n in names]
    ax = axes[0, 0]
    ax.bar(x - 0.2, prior, 0.4, label="prior")
    ax.bar(x + 0.2, [scores[n].post_mae_um for n in names], 0.4, label="posterior")
    ax.set_ylabel("mean absolute error (um)")
    ax.legend()
    panels = [
        (axes[0, 1], [scores[n].in_focus_fraction for n in names], "in-focus fraction"),
        (axes[1, 0], [scores[n].images_per_tile for n in names], "images per tile"),
        (axes[1, 1], [scores[n].scan_time_s for n in names], "scan time per map (s)"),
    ]
    for panel, values, label in panels:
        panel.bar(x, values, 0.6, color="tab:gray")
        panel.set_ylabel(label)
    for panel in axes.flat:
        panel.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
    fig.suptitle(map_set.title, fontsize=10)
    summary_path = directory / f"summary_{_slug(map_set.name)}.png"
    fig.savefig(summary_path, dpi=110)
    plt.close(fig)
    return [heat_path, summary_path]


def _scores_json(scores: dict[str, Scores]) -> dict[str, dict[str, float | None]]:
    return {name: asdict(s) for name, s in scores.items()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    generated = parser.add_argument_group("generated maps")
    generated.add_argument(
        "--maps", type=count_number, default=None, help="number of maps (default 16)"
    )
    generated.add_argument(
        "--size",
        type=whole_number(2, MAX_GRID_SIDE),
        default=None,
        help="tiles per side, >= 2 (default 20)",
    )
    generated.add_argument(
        "--family",
        action="extend",
        nargs="+",
        choices=sorted(FAMILIES),
        help=f"map family or families (several, or repeated), each reported apart "
        f"(default {DEFAULT_FAMILY})",
    )
    user = parser.add_argument_group("a user's maps")
    user.add_argument(
        "--truth-map",
        type=Path,
        help="true focus map(s) in um: .npy, .csv or .tif, 2-D or 3-D (several maps)",
    )
    user.add_argument(
        "--measured-map",
        type=Path,
        help="measured best focus of every tile, replayed as given (shape of --truth-map)",
    )
    parser.add_argument(
        "--seed",
        type=seed_number,
        default=1000,
        help="seed of the maps and the noise (default 1000)",
    )
    parser.add_argument(
        "--noise-um",
        type=positive_float,
        default=1.5,
        help="std of simulated measurement noise in um; also the noise the filters assume "
        "(default 1.5)",
    )
    parser.add_argument(
        "--dof-um", type=positive_float, default=1.0, help="depth of field in um (default 1.0)"
    )
    parser.add_argument(
        "--strategies",
        nargs="+",
        metavar="NAME",
        help="strategies to run, space- or comma-separated (default: all registered)",
    )
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the scores as JSON")
    parser.add_argument("--plots", type=output_folder, metavar="DIR", help="write PNG plots to DIR")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _map_sets(args: argparse.Namespace) -> list[MapSet]:
    """The map sets the arguments ask for; raises ValueError on a contradiction."""
    if args.truth_map is None:
        if args.measured_map is not None:
            raise ValueError("--measured-map needs --truth-map")
        n_maps = 16 if args.maps is None else args.maps
        size = 20 if args.size is None else args.size
        families = list(dict.fromkeys(args.family or [DEFAULT_FAMILY]))
        return generated_map_sets(families, n_maps, size, args.seed, args.noise_um)
    generated_only = {"--maps": args.maps, "--size": args.size, "--family": args.family}
    given = [flag for flag, value in generated_only.items() if value is not None]
    if given:
        raise ValueError(f"{', '.join(given)} apply to generated maps, not to --truth-map")
    return [user_map_set(args.truth_map, args.measured_map, args.noise_um, args.seed)]


def run(args: argparse.Namespace) -> int:
    try:
        default = [name for name in registry.STRATEGIES if name not in ELSEWHERE]
        names = [n for item in args.strategies or default for n in item.split(",")]
        names = list(dict.fromkeys(n for n in names if n))
        unknown = [n for n in names if n not in registry.STRATEGIES]
        if unknown or not names:
            raise ValueError(
                f"unknown strategy {', '.join(unknown) or '(none given)'}; "
                f"known: {', '.join(registry.STRATEGIES)}"
            )
        map_sets = _map_sets(args)
        if ORACLE in names and any(map_set.spec is None for map_set in map_sets):
            if args.strategies:
                raise ValueError(f"{ORACLE} needs generated maps: it is given their SurfaceSpec")
            names.remove(ORACLE)  # not asked for by name: run every other strategy
        for map_set in map_sets:  # a strategy that cannot scan these maps fails now, not midway
            grid = ScanGrid(*map_set.truth_um.shape[1:])
            for name in names:
                registry.create(name, default_settings(grid))
    except (ValueError, OSError) as error:
        print(f"focustrack bench accuracy: error: {error}", file=sys.stderr)
        return 2

    results = replay_all(map_sets, names, args.noise_um, args.dof_um, progress=not args.no_progress)
    families: dict[str, object] = {}
    for map_set in map_sets:
        replays = results[map_set.name]
        scores = score_with_smoothed(replays, args.dof_um)
        print()
        conditions = f"noise {args.noise_um} um, depth of field {args.dof_um} um"
        print(format_table(f"{map_set.title}; {conditions}", scores))
        calibration = {
            name: reliability(replays[name], args.dof_um) for name in names if stated_risk(name) > 0
        }
        floor = 1.0 - scores[ORACLE].in_focus_fraction if ORACLE in scores else None
        for name, bins in calibration.items():
            print(format_reliability(name, bins, stated_risk(name), scores[name], floor))
        families[map_set.name] = {
            "title": map_set.title,
            "maps": map_set.n_maps,
            "strategies": _scores_json(scores),
            "reliability": {name: [asdict(b) for b in bins] for name, bins in calibration.items()},
        }
        if args.plots is not None:
            for path in write_plots(args.plots, map_set, replays, scores):
                print(f"wrote {path}")
    # Top-level scores pool every map replayed (the one family's, when there is one).
    pooled = score_with_smoothed(
        {name: [r for by_name in results.values() for r in by_name[name]] for name in names},
        args.dof_um,
    )
    report = {
        "strategies": _scores_json(pooled),
        "families": families,
        "noise_um": args.noise_um,
        "dof_um": args.dof_um,
        "seed": args.seed,
    }
    if args.json is not None:
        write_json(args.json, report)
        print(f"wrote {args.json}")
    return 0
