"""True focus surfaces of slides: generated from a seed, or loaded from a user's file.

A surface z*(row, col) in um is the sum of
- a stationary Gaussian random field with an exponential covariance
  ``field_sigma_um**2 * exp(-3 d / range_tiles)`` (d in tiles; the variogram
  reaches 95% of its sill at ``range_tiles``), smoothed with a Gaussian of
  ``smooth_sigma_tiles`` as the ground truth of the thesis is;
- a random plane (slide tilt) and a random quadratic (cover-glass bend), whose
  coefficients are zero-mean Gaussians;
- optionally a step of ``step_um`` across a random straight line (a fold, an
  edge of the smear), smoothed the same way.

The field is made spectrally on a torus padded by a few ranges, so its
covariance is known exactly (`surface_covariance`): the Bayes-optimal
estimator of the benchmark (`gp-oracle`) uses it; no scanner may.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class SurfaceSpec:
    """Parameters of generated surfaces. Lengths in tiles, heights in um.

    The defaults make maps as hard as the thesis' malaria-smear maps: on them,
    with 1.5 um measurement noise, the 0th-order Wiener filter's prior MAE is
    about 0.7 um (thesis Table 3-1: 0.697 um) and the Bayes-optimal prior about
    0.4 um.
    """

    rows: int = 20
    cols: int = 20
    field_sigma_um: float = 1.0
    range_tiles: float = 15.0
    tilt_sigma_um_per_tile: float = 0.1
    bend_sigma_um: float = 1.0
    step_um: float = 0.0
    smooth_sigma_tiles: float = 1.0

    def __post_init__(self) -> None:
        if self.rows < 1 or self.cols < 1:
            raise ValueError(f"surface must have at least one tile, got {self.rows}x{self.cols}")
        if self.range_tiles <= 0 or self.field_sigma_um < 0 or self.smooth_sigma_tiles < 0:
            raise ValueError("range_tiles must be positive; sigmas must not be negative")

    @property
    def torus_shape(self) -> tuple[int, int]:
        """The periodic grid the field is drawn on, padded so wrap-around is negligible."""
        pad = int(np.ceil(2 * self.range_tiles + 4 * self.smooth_sigma_tiles))
        return (self.rows + pad, self.cols + pad)


#: Map families of the benchmark: name -> spec changes from the defaults.
FAMILIES: dict[str, dict[str, float]] = {
    "standard": {},
    "steps": {"step_um": 4.0},
    "tilted": {"tilt_sigma_um_per_tile": 1.0, "field_sigma_um": 0.5},
    "rough": {"field_sigma_um": 2.0, "range_tiles": 8.0},
    # Standard surfaces; the benchmark adds measurement outliers (dust, a parasite in
    # another plane) to 5% of their tiles (`focustrack.bench.accuracy.OUTLIERS`).
    "outliers": {},
}


def family_spec(name: str, rows: int = 20, cols: int = 20) -> SurfaceSpec:
    """The `SurfaceSpec` of a named map family (see `FAMILIES`)."""
    if name not in FAMILIES:
        raise ValueError(f"unknown map family {name!r}; known: {', '.join(FAMILIES)}")
    return replace(SurfaceSpec(rows=rows, cols=cols), **FAMILIES[name])  # type: ignore[arg-type]


def _field_kernel(spec: SurfaceSpec) -> np.ndarray:
    """Covariance (um^2) of the smoothed random field against torus lag (dy, dx)."""
    ny, nx = spec.torus_shape
    dy = np.minimum(np.arange(ny), ny - np.arange(ny))[:, None]
    dx = np.minimum(np.arange(nx), nx - np.arange(nx))[None, :]
    distance = np.hypot(dy, dx)
    kernel = spec.field_sigma_um**2 * np.exp(-3.0 * distance / spec.range_tiles)
    spectrum = np.clip(np.fft.fft2(kernel).real, 0.0, None)
    spectrum *= _gaussian_transfer(spec) ** 2
    return np.fft.ifft2(spectrum).real


def _gaussian_transfer(spec: SurfaceSpec) -> np.ndarray:
    """Transfer function of the Gaussian smoothing on the torus grid."""
    ny, nx = spec.torus_shape
    fy = np.fft.fftfreq(ny)[:, None]
    fx = np.fft.fftfreq(nx)[None, :]
    return np.exp(-2.0 * np.pi**2 * spec.smooth_sigma_tiles**2 * (fx**2 + fy**2))


def _centred_coords(spec: SurfaceSpec) -> tuple[np.ndarray, np.ndarray]:
    """Tile coordinates (y, x) relative to the map centre, in tiles, shape (rows, cols)."""
    y = np.arange(spec.rows) - (spec.rows - 1) / 2.0
    x = np.arange(spec.cols) - (spec.cols - 1) / 2.0
    return np.meshgrid(y, x, indexing="ij")


def _bend_basis(spec: SurfaceSpec, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The three quadratic shapes, each 1 um at the map's half-diagonal; shape (3, ...)."""
    half = max(spec.rows, spec.cols) / 2.0
    u, v = x / half, y / half
    return np.stack([u * u, v * v, u * v])


def generate_surface(spec: SurfaceSpec, rng: np.random.Generator) -> np.ndarray:
    """One true focus surface, shape (rows, cols), in um."""
    ny, nx = spec.torus_shape
    spectrum = np.clip(np.fft.fft2(_field_kernel(spec)).real, 0.0, None)
    white = rng.standard_normal((ny, nx))
    field = np.fft.ifft2(np.sqrt(spectrum) * np.fft.fft2(white)).real
    offset = rng.integers(0, (ny, nx))
    field = np.roll(field, -offset, axis=(0, 1))[: spec.rows, : spec.cols]

    y, x = _centred_coords(spec)
    slope_y, slope_x = rng.normal(0.0, spec.tilt_sigma_um_per_tile, size=2)
    bend = rng.normal(0.0, spec.bend_sigma_um, size=3)
    trend = slope_y * y + slope_x * x + np.tensordot(bend, _bend_basis(spec, y, x), axes=1)

    surface = field + trend
    if spec.step_um:
        angle = rng.uniform(0.0, np.pi)
        through = rng.uniform(-0.3, 0.3, size=2) * (spec.rows, spec.cols)
        side = (y - through[0]) * np.cos(angle) - (x - through[1]) * np.sin(angle) > 0
        step = np.where(side, spec.step_um, 0.0)
        # Imported here: the instrument's `--help` lists FAMILIES without loading scipy.
        from scipy import ndimage

        surface += ndimage.gaussian_filter(step, spec.smooth_sigma_tiles, mode="nearest")
    return surface


def generate_surfaces(spec: SurfaceSpec, n_maps: int, seed: int) -> np.ndarray:
    """`n_maps` independent surfaces, shape (n_maps, rows, cols); deterministic from `seed`."""
    return np.stack(
        [generate_surface(spec, np.random.default_rng([seed, index])) for index in range(n_maps)]
    )


def surface_covariance(spec: SurfaceSpec, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Exact prior covariance (um^2) of generated surfaces between the given tiles.

    `rows` and `cols` are integer arrays of shape (n,); returns (n, n). Exact
    for surfaces without a step (the step is not Gaussian).
    """
    ny, nx = spec.torus_shape
    kernel = _field_kernel(spec)
    rows, cols = np.asarray(rows), np.asarray(cols)
    field = kernel[(rows[:, None] - rows[None, :]) % ny, (cols[:, None] - cols[None, :]) % nx]
    y = rows - (spec.rows - 1) / 2.0
    x = cols - (spec.cols - 1) / 2.0
    tilt = spec.tilt_sigma_um_per_tile**2 * (np.outer(y, y) + np.outer(x, x))
    basis = _bend_basis(spec, y, x)
    bend = spec.bend_sigma_um**2 * np.einsum("kn,km->nm", basis, basis)
    return field + tilt + bend


def load_map(path: str | Path) -> np.ndarray:
    """A user's focus map(s) in um: 2-D (rows, cols) or 3-D (n_maps, rows, cols).

    Reads `.npy`, `.csv` (comma-separated, one row of tiles per line) and
    `.tif`/`.tiff` (a single page, or several pages of one shape).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        array = np.load(path, allow_pickle=False)
    elif suffix == ".csv":
        array = np.loadtxt(path, delimiter=",", ndmin=2)
    elif suffix in (".tif", ".tiff"):
        import tifffile

        array = tifffile.imread(path)
    else:
        raise ValueError(f"{path}: unsupported map format {suffix!r} (use .npy, .csv or .tif)")
    array = np.asarray(array, dtype=float)
    if array.ndim not in (2, 3) or min(array.shape) < 1:
        raise ValueError(f"{path}: expected a 2-D map or a 3-D stack of maps, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{path}: map contains NaN or infinite heights")
    return array


# --- Measured maps: a truth as a best-focus search would see it. ---


def add_measurement_noise(truth_um: np.ndarray, noise_um: float, seed: int) -> np.ndarray:
    """Truth (n_maps, rows, cols) plus Gaussian noise of std `noise_um`; map i's from (seed, i).

    The noise stream is separate from the surface generator's (which uses (seed, i)
    too), so the noise does not depend on the family or the size of a map.
    """
    noise = [
        np.random.default_rng([seed, index, 1]).standard_normal(truth.shape)
        for index, truth in enumerate(truth_um)
    ]
    return truth_um + noise_um * np.stack(noise)


@dataclass(frozen=True)
class Outliers:
    """Gross measurement errors: a `fraction` of tiles off by `low_um`..`high_um`, either sign.

    What dust or a parasite lying in another plane does to a best-focus search:
    the peak it finds is several um from the specimen's, whatever the noise.
    """

    fraction: float
    low_um: float
    high_um: float


#: Map families whose measurements also carry outliers (their surfaces are in FAMILIES).
OUTLIERS: dict[str, Outliers] = {"outliers": Outliers(fraction=0.05, low_um=3.0, high_um=8.0)}


def add_outliers(measured_um: np.ndarray, outliers: Outliers, seed: int) -> np.ndarray:
    """Measured maps (n_maps, rows, cols) with outliers; map i's drawn from (seed, i, 2)."""
    corrupted = measured_um.copy()
    for index, measured in enumerate(corrupted):
        rng = np.random.default_rng([seed, index, 2])
        hit = rng.random(measured.shape) < outliers.fraction
        size_um = rng.uniform(outliers.low_um, outliers.high_um, measured.shape)
        measured += np.where(hit, rng.choice([-1.0, 1.0], measured.shape) * size_um, 0.0)
    return corrupted
