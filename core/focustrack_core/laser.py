"""A reflection (laser) autofocus: it reads the coverslip, not the tissue.

Hardware autofocus (Nikon PFS, Zeiss Definite Focus, a scanner's laser autofocus)
reflects a beam off the glass-coverslip interface and reads its height in about a
millisecond. The interface moves with the stage and the drift, so the reading
tracks both; but the tissue's focal plane lies an unknown offset from the glass
(section thickness, mounting medium, coverslip tilt) that varies slowly over the
slide. So a reading at tile (r, c) at time t is

    laser(r, c, t) = focus(r, c, t) - offset(r, c) + e,   e ~ N(0, noise_um^2),

focus the tissue's best focus then (drift included) and offset a smooth random
field (`coverslip_offsets`: mean `offset_um`, std `offset_sigma_um`, correlation
length `offset_length_tiles`), drawn per seed. Shared by the simulator's sensor and
the benchmarks' replay, so that both read the same glass. Heights in um.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LaserSpec:
    """The sensor: its noise, the offsets' statistics and the time of one reading."""

    noise_um: float = 0.05
    offset_um: float = 4.0
    offset_sigma_um: float = 0.4
    offset_length_tiles: float = 10.0
    reading_s: float = 0.001

    def __post_init__(self) -> None:
        if not (self.noise_um >= 0 and self.offset_sigma_um >= 0 and self.reading_s >= 0):
            raise ValueError(
                "the laser's noise, offset sigma and reading time must not be negative"
            )
        if not self.offset_length_tiles > 0:
            raise ValueError(
                f"offset_length_tiles must be positive, got {self.offset_length_tiles}"
            )


def coverslip_offsets(shape: tuple[int, int], seed: int, spec: LaserSpec) -> np.ndarray:
    """The tissue's focal plane above the coverslip interface at each tile, (rows, cols) um.

    White noise smoothed by a Gaussian of `offset_length_tiles` (in Fourier space, on a
    grid twice the size so that the edges do not wrap), scaled so that the field's std
    (over slides, not over one small grid) is `offset_sigma_um`, about `offset_um`.
    """
    rows, cols = shape
    rng = np.random.default_rng([seed, 11])
    noise = rng.standard_normal((2 * rows, 2 * cols))
    fy = np.fft.fftfreq(2 * rows)[:, None]
    sigma = spec.offset_length_tiles

    def transfer(fx: np.ndarray) -> np.ndarray:
        return np.exp(-2.0 * (np.pi * sigma) ** 2 * (fx**2 + fy**2))

    smoothed = np.fft.irfft2(
        np.fft.rfft2(noise) * transfer(np.fft.rfftfreq(2 * cols)), s=noise.shape
    )
    # unit white noise through the filter: variance = the mean of |transfer|^2 over the grid
    std = float(np.sqrt(np.mean(transfer(np.fft.fftfreq(2 * cols)) ** 2)))
    return spec.offset_um + spec.offset_sigma_um / std * smoothed[:rows, :cols]


def laser_reading(
    focus_um: float, offset_um: float, noise_um: float, rng: np.random.Generator
) -> float:
    """One reading, um: the interface under a tissue in focus at `focus_um`, with noise."""
    return float(focus_um - offset_um + noise_um * rng.standard_normal())
