"""Tune the Kalman strategies' parameters and the stack width on TRAINING maps.

The defaults of `focustrack_estimator.kalman_strategies` (and of the
model bank, `bank.kf_mmae`) come from here: maps generated from seeds 0..4 (16
maps each, of the `--families` asked for: `standard`, the `SurfaceSpec()`
defaults, unless told otherwise), measured with Gaussian noise (and outliers
for the `outliers` family); the benchmark reports on other seeds (1000+), so no
default is ever tuned on a map it is judged on. The objective pools every
family's maps, so one default serves them all.

Two stages:
1. accuracy: a coordinate search over each strategy's parameter grid
   (`SEARCH_SPACE`), minimising prior MAE + posterior MAE (the prior places the
   stack, the posterior is where the tile is imaged). Accuracy does not depend
   on the stack width in the replay (a missed peak is re-acquired), so this
   stage uses the default `ZRangePolicy`;
2. cost: a sweep of `ZRangePolicy.k_sigma` at the tuned parameters, reporting
   images per tile and scan time (narrow stacks miss the peak more often, and
   every miss costs a `max_frames` retry stack).

Run: `python -m focustrack.bench.tune [--seeds 10] [--plots DIR]` (or wire
`add_arguments`/`run` to a CLI subcommand). See docs/estimators.md for results.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from focustrack.arguments import count_number, output_folder, positive_float, positive_int
from focustrack.bench.strategies import create, parameters
from focustrack_core.domain import ZRangePolicy
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_policy, default_settings
from focustrack_core.surfaces import (
    FAMILIES,
    OUTLIERS,
    add_outliers,
    family_spec,
    generate_surfaces,
)
from focustrack_estimator.replay import Scores, replay, score

_Q_HEIGHT_UM2 = [0.0, 0.01, 0.03, 0.1, 0.2, 0.3]

#: Parameter grids of the coordinate search, per strategy (units as in the factories).
SEARCH_SPACE: dict[str, dict[str, list[Any]]] = {
    "kf-wiener0": {"q": [0.03, 0.05, 0.07, 0.1, 0.14, 0.2, 0.3, 0.5]},
    "kf-wiener1": {
        "q": [1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2],
        "q_height_um2": _Q_HEIGHT_UM2,
    },
    "kf-wiener2": {"q": [1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4], "q_height_um2": _Q_HEIGHT_UM2},
    "kf-gm1": {
        "sigma": [0.3, 0.5, 0.7, 1.0, 1.4, 2.0],
        "beta_per_tile": [6.0, 8.0, 12.0, 20.0],
        "q_height_um2": _Q_HEIGHT_UM2,
    },
    "kf-gm2": {
        "sigma": [0.01, 0.03, 0.1, 0.3, 1.0],
        "beta_per_tile": [21.0, 30.0, 50.0, 100.0],
        "q_height_um2": _Q_HEIGHT_UM2,
    },
    "kf-wiener1-dir": {
        "q": [1e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2],
        "q_height_um2": _Q_HEIGHT_UM2,
        "partitioned": [True, False],
    },
    "kf-mmae": {
        "q_spread": [3.0, 10.0, 30.0],
        "q_height_um2": [0.03, 0.1, 0.3],
        "gate_nis": [0.0, 9.0, 16.0, 25.0],
        "nis_clip": [4.0, 9.0],
    },
}

K_SIGMAS = (1.5, 1.75, 2.0, 2.25, 2.5, 3.0)


@dataclass(frozen=True)
class TrainingSet:
    """True and measured maps, each (n_maps, rows, cols) in um."""

    truth_um: np.ndarray
    measured_um: np.ndarray


def training_set(
    seeds: Iterable[int],
    maps_per_seed: int,
    noise_um: float,
    families: Iterable[str] = ("standard",),
) -> TrainingSet:
    """`maps_per_seed` surfaces per seed and family, plus Gaussian noise of `noise_um` (std, um).

    Maps of the `outliers` family get its outliers too (`accuracy.OUTLIERS`).
    """
    truths, measured = [], []
    for family in families:
        for seed in seeds:
            truth = generate_surfaces(family_spec(family), maps_per_seed, seed)
            noisy = truth + np.random.default_rng(seed).normal(0.0, noise_um, truth.shape)
            if family in OUTLIERS:
                noisy = add_outliers(noisy, OUTLIERS[family], seed)
            truths.append(truth)
            measured.append(noisy)
    return TrainingSet(np.concatenate(truths), np.concatenate(measured))


def evaluate(
    name: str,
    params: dict[str, Any],
    data: TrainingSet,
    policy: ZRangePolicy | None = None,
    noise_um: float = 1.5,
) -> Scores:
    """Scores of strategy `name` with `params` over every map of `data`."""
    rows, cols = data.truth_um.shape[1:]
    changes = {} if policy is None else {"policy": policy}  # none: the API's default policy
    settings = default_settings(ScanGrid(rows, cols), noise_sigma_um=noise_um, **changes)
    replays = [
        replay(create(name, settings, params), truth, measured)
        for truth, measured in zip(data.truth_um, data.measured_um, strict=True)
    ]
    return score(replays, settings.dof_um)


def objective(scores: Scores) -> float:
    """What the accuracy stage minimises, in um."""
    return (scores.prior_mae_um or 0.0) + scores.post_mae_um


# Worker processes hold the training set once, instead of receiving it with every task.
_WORKER_DATA: TrainingSet | None = None


def _init_worker(data: TrainingSet) -> None:
    global _WORKER_DATA
    _WORKER_DATA = data


def _evaluate_in_worker(task: tuple[str, dict[str, Any], ZRangePolicy | None]) -> Scores:
    assert _WORKER_DATA is not None
    return evaluate(*task[:2], _WORKER_DATA, task[2])


def _format(params: dict[str, Any]) -> str:
    return " ".join(
        f"{key}={value:g}" if isinstance(value, float) else f"{key}={value}"
        for key, value in params.items()
    )


def coordinate_search(
    name: str,
    space: dict[str, list[Any]],
    run: Callable[[list[dict[str, Any]]], list[Scores]],
    passes: int = 2,
    log: Callable[[str], None] = print,
) -> tuple[dict[str, Any], Scores]:
    """Minimise `objective` one parameter at a time over its grid, `passes` times round.

    `run` scores a batch of parameter sets (so it may run them in parallel).
    Starts from the factory's current defaults; returns the best set and its scores.
    """
    defaults = {key: value for key, value in parameters(name).items() if key in space}
    seen: dict[tuple, Scores] = {}

    def batch(candidates: list[dict[str, Any]]) -> None:
        fresh = [c for c in candidates if _key(c) not in seen]
        for candidate, scores in zip(fresh, run(fresh), strict=True):
            seen[_key(candidate)] = scores
            log(
                f"  {name:15s} {_format(candidate):45s} prior {scores.prior_mae_um:.3f}  "
                f"post {scores.post_mae_um:.3f} um"
            )

    best = dict(defaults)
    batch([best])
    for _ in range(passes):
        for key, grid in space.items():
            candidates = [{**best, key: value} for value in grid]
            batch(candidates)
            best = min([best, *candidates], key=lambda c: objective(seen[_key(c)]))
    return best, seen[_key(best)]


def _key(params: dict[str, Any]) -> tuple:
    return tuple(sorted(params.items()))


def tune(
    seeds: Iterable[int] = range(5),
    maps_per_seed: int = 16,
    noise_um: float = 1.5,
    names: Iterable[str] = tuple(SEARCH_SPACE),
    families: Iterable[str] = ("standard",),
    k_sigmas: Iterable[float] = K_SIGMAS,
    workers: int | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, dict[str, Any]]:
    """Tune every strategy in `names`; returns {name: {"params", "scores", "k_sigma"}}.

    "k_sigma" maps each k of the sweep to the Scores at the tuned parameters.
    """
    families = list(families)
    data = training_set(seeds, maps_per_seed, noise_um, families)
    log(
        f"training set: {data.truth_um.shape[0]} maps of {data.truth_um.shape[1:]} tiles "
        f"({', '.join(families)}), noise {noise_um} um"
    )
    results: dict[str, dict[str, Any]] = {}
    with ProcessPoolExecutor(
        workers or os.cpu_count(), initializer=_init_worker, initargs=(data,)
    ) as pool:
        for name in names:
            log(f"{name}: accuracy search")

            def run(candidates: list[dict[str, Any]], name: str = name) -> list[Scores]:
                return list(pool.map(_evaluate_in_worker, [(name, c, None) for c in candidates]))

            params, scores = coordinate_search(name, SEARCH_SPACE[name], run, log=log)
            log(f"{name}: best {_format(params)}; stack width sweep")
            policies = [default_policy(k_sigma=k) for k in k_sigmas]
            sweep = list(pool.map(_evaluate_in_worker, [(name, params, p) for p in policies]))
            for k, swept in zip(k_sigmas, sweep, strict=True):
                log(
                    f"  k_sigma {k:4.2f}: {swept.images_per_tile:5.2f} images/tile, "
                    f"{swept.scan_time_s:6.1f} s/map, in focus {swept.in_focus_fraction:.3f}"
                )
            results[name] = {
                "params": params,
                "scores": scores,
                "k_sigma": dict(zip(k_sigmas, sweep, strict=True)),
            }
    log(summary_table(results))
    return results


def summary_table(results: dict[str, dict[str, Any]]) -> str:
    """The tuned parameters and their training scores, one line per strategy."""
    lines = [
        f"{'strategy':15s} {'prior MAE':>9s} {'std':>6s} {'post MAE':>9s} {'std':>6s} "
        f"{'best k':>6s}  parameters"
    ]
    for name, result in results.items():
        s: Scores = result["scores"]
        best_k = min(result["k_sigma"], key=lambda k: result["k_sigma"][k].scan_time_s)
        lines.append(
            f"{name:15s} {s.prior_mae_um:9.3f} {s.prior_std_um:6.3f} "
            f"{s.post_mae_um:9.3f} {s.post_std_um:6.3f} {best_k:6.2f}  "
            f"{_format(result['params'])}"
        )
    return "\n".join(lines)


def plot_k_sigma(results: dict[str, dict[str, Any]], path: Path) -> None:
    """PNG of images per tile and scan time against k_sigma, one line per strategy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (images_ax, time_ax) = plt.subplots(1, 2, figsize=(10, 4))
    for name, result in results.items():
        ks = sorted(result["k_sigma"])
        images_ax.plot(ks, [result["k_sigma"][k].images_per_tile for k in ks], "o-", label=name)
        time_ax.plot(ks, [result["k_sigma"][k].scan_time_s for k in ks], "o-", label=name)
    images_ax.set(xlabel="k_sigma", ylabel="images per tile")
    time_ax.set(xlabel="k_sigma", ylabel="scan time per 20x20 map (s)")
    images_ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=count_number, default=5, help="training seeds 0..N-1")
    parser.add_argument("--maps-per-seed", type=count_number, default=16)
    parser.add_argument("--noise-um", type=positive_float, default=1.5)
    parser.add_argument(
        "--strategies", nargs="+", default=list(SEARCH_SPACE), choices=list(SEARCH_SPACE)
    )
    parser.add_argument(
        "--families",
        nargs="+",
        default=["standard"],
        choices=sorted(FAMILIES),
        help="map families of the training set, pooled (default standard)",
    )
    parser.add_argument(
        "--workers", type=positive_int, default=None, help="processes (default: cores)"
    )
    parser.add_argument("--plots", type=output_folder, default=None, help="write k_sigma.png here")


def run(args: argparse.Namespace) -> int:
    results = tune(
        range(args.seeds),
        args.maps_per_seed,
        args.noise_um,
        args.strategies,
        args.families,
        workers=args.workers,
    )
    if args.plots:
        args.plots.mkdir(parents=True, exist_ok=True)
        plot_k_sigma(results, args.plots / "k_sigma.png")
        print(f"wrote {args.plots / 'k_sigma.png'}")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m focustrack.bench.tune", description=__doc__)
    add_arguments(parser)
    raise SystemExit(run(parser.parse_args()))
