"""The 2-D estimators on the thesis protocol, as ratios to the Gaussian-process oracle.

Maps: `generate_surfaces(family_spec(family), n_maps, seed)` plus Gaussian
measurement noise (`focustrack_core.surfaces.add_measurement_noise`); every
strategy is replayed on the same measurements (`focustrack_estimator.replay`).
`gp-oracle` is given the family's `SurfaceSpec`; no other strategy knows it.

Run: `python -m focustrack.bench.spatial_eval [--maps 16] [--seed 1000]
[--family standard] [--noise-um 1.5] [--plot FILE.png]` (docs/spatial.md).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from focustrack.arguments import count_number, output_file, seed_number
from focustrack.bench import strategies as registry
from focustrack.bench.accuracy import format_table
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import add_measurement_noise, family_spec, generate_surfaces
from focustrack_estimator.replay import Scores, replay, score

DEFAULT_NAMES = ("gp-oracle", "kf-2d", "nshp-wiener1", "nshp-wiener0", "kf-wiener0")


def evaluate(
    names: Sequence[str],
    *,
    n_maps: int = 16,
    seed: int = 1000,
    family: str = "standard",
    noise_um: float = 1.5,
    dof_um: float = 1.0,
    progress: bool = True,
) -> dict[str, Scores]:
    """Scores of each named strategy (spatial ones and the registry's) on one map family."""
    known = registry.STRATEGIES
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ValueError(f"unknown strategy {', '.join(unknown)}; known: {', '.join(known)}")
    spec = family_spec(family)
    truth_um = generate_surfaces(spec, n_maps, seed)
    measured_um = add_measurement_noise(truth_um, noise_um, seed)
    settings = default_settings(ScanGrid(spec.rows, spec.cols), noise_sigma_um=noise_um)
    scores = {}
    for name in names:
        params = asdict(spec) if name == "gp-oracle" else {}
        runs = [
            replay(registry.create(name, settings, params), truth, measured)
            for truth, measured in tqdm(
                list(zip(truth_um, measured_um, strict=True)), desc=name, disable=not progress
            )
        ]
        scores[name] = score(runs, dof_um)
    return scores


def ratio_table(title: str, scores: dict[str, Scores], reference: str = "gp-oracle") -> str:
    """`format_table` plus each strategy's prior and posterior MAE over the reference's."""
    table = format_table(title, scores)
    if reference not in scores:
        return table
    ref = scores[reference]
    lines = [f"\nMAE as a ratio to {reference}:", f"{'strategy':<18}{'prior':>8}{'post':>8}"]
    for name, s in scores.items():
        prior = (
            "-"
            if s.prior_mae_um is None or ref.prior_mae_um is None
            else f"{s.prior_mae_um / ref.prior_mae_um:.3f}"
        )
        lines.append(f"{name:<18}{prior:>8}{s.post_mae_um / ref.post_mae_um:>8.3f}")
    return table + "\n" + "\n".join(lines)


def plot(scores: dict[str, Scores], path: Path, title: str) -> None:
    """Prior and posterior MAE per strategy as a bar chart (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = list(scores)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2, 4))
    prior = [scores[n].prior_mae_um or 0.0 for n in names]
    ax.bar(x - 0.2, prior, 0.4, label="prior MAE")
    ax.bar(x + 0.2, [scores[n].post_mae_um for n in names], 0.4, label="posterior MAE")
    ax.set_xticks(x, names)
    ax.set_ylabel("mean absolute error (um)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", type=count_number, default=16)
    parser.add_argument("--seed", type=seed_number, default=1000)
    parser.add_argument("--family", default="standard")
    parser.add_argument("--noise-um", type=float, default=1.5)
    parser.add_argument("--strategies", default=",".join(DEFAULT_NAMES))
    parser.add_argument("--plot", type=output_file, help="write a PNG bar chart here")
    args = parser.parse_args(argv)
    try:
        names = [n for n in args.strategies.split(",") if n]
        scores = evaluate(
            names, n_maps=args.maps, seed=args.seed, family=args.family, noise_um=args.noise_um
        )
    except ValueError as error:
        parser.error(str(error))
    title = f"{args.family}: {args.maps} maps, seed {args.seed}, noise {args.noise_um} um"
    print(ratio_table(title, scores))
    if args.plot:
        plot(scores, args.plot, title)
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
