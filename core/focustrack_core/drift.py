"""Thermal z drift of a microscope over a scan: settling after start plus a random walk.

A stage and objective warm up after the instrument starts; focus moves most in
the first minutes, then wanders. Modelled as

    d(t) = settle_um (1 - exp(-t / settle_tau_s)) + w(t),

w a Wiener process (random walk) with std `walk_um_per_sqrt_min` after one
minute (variance walk^2 t / 60 s). The settling term is what a first-order
Gauss-Markov rate of time constant `settle_tau_s` integrates to (the estimators'
time state, `focustrack_estimator.time_state`, has that shape). The walk is
drawn per seed on a fixed grid of `WALK_STEP_S` and linearly interpolated, in
chunks seeded by their index, so that d(t) at any time, asked in any order, is
the same for a seed. Shared by the simulator's stage and the benchmarks' replay,
so that both see the same drift. Times in s from the scan's start, heights in um.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Spacing of the random walk's grid, s: well below a row of tiles (several seconds).
WALK_STEP_S = 1.0

#: Grid points of the walk drawn at once (one hour at `WALK_STEP_S`).
CHUNK_STEPS = 3600


@dataclass
class ThermalDrift:
    """d(t) in um for t in s (see the module docstring); all zero: no drift.

    settle_um: the amplitude of the settling, um (d tends to it); settle_tau_s: its
    time constant, s; walk_um_per_sqrt_min: the random walk's std after one minute,
    um.
    """

    settle_um: float = 0.0
    settle_tau_s: float = 200.0
    walk_um_per_sqrt_min: float = 0.0
    seed: int = 0
    _chunks: dict[int, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.settle_tau_s > 0:
            raise ValueError(f"settle_tau_s must be positive, got {self.settle_tau_s}")
        if self.walk_um_per_sqrt_min < 0:
            raise ValueError(
                f"walk_um_per_sqrt_min must not be negative, got {self.walk_um_per_sqrt_min}"
            )

    @classmethod
    def thermal(cls, seed: int) -> ThermalDrift:
        """The benchmarks' thermal scenario: 2 um settling over 10 min (tau 200 s, 95%
        settled at 10 min), then a random walk of 0.3 um per sqrt(minute)."""
        return cls(settle_um=2.0, settle_tau_s=200.0, walk_um_per_sqrt_min=0.3, seed=seed)

    def _chunk(self, index: int) -> np.ndarray:
        """The walk at grid points index*CHUNK_STEPS .. (index+1)*CHUNK_STEPS (inclusive)."""
        if index not in self._chunks:
            start = 0.0 if index == 0 else float(self._chunk(index - 1)[-1])
            sigma_um = self.walk_um_per_sqrt_min * math.sqrt(WALK_STEP_S / 60.0)
            steps = np.random.default_rng([self.seed, 7, index]).standard_normal(CHUNK_STEPS)
            self._chunks[index] = start + np.concatenate([[0.0], np.cumsum(sigma_um * steps)])
        return self._chunks[index]

    def walk_um(self, t_s: np.ndarray | float) -> np.ndarray:
        """The random walk w(t), um, at `t_s` (>= 0; any shape)."""
        t = np.maximum(np.asarray(t_s, dtype=float), 0.0)
        if self.walk_um_per_sqrt_min == 0:
            return np.zeros_like(t)
        steps = t / WALK_STEP_S
        index = np.floor(steps / CHUNK_STEPS).astype(int)
        out = np.empty_like(t)
        for chunk in np.unique(index):
            inside = index == chunk
            grid = self._chunk(int(chunk))
            local = steps[inside] - chunk * CHUNK_STEPS
            out[inside] = np.interp(local, np.arange(CHUNK_STEPS + 1), grid)
        return out

    def at(self, t_s: float) -> float:
        """d(t_s) in um (a float)."""
        return float(self.array(np.asarray(t_s, dtype=float)))

    def array(self, t_s: np.ndarray) -> np.ndarray:
        """d at each of `t_s` (any shape), um."""
        t = np.asarray(t_s, dtype=float)
        settle = self.settle_um * -np.expm1(-np.maximum(t, 0.0) / self.settle_tau_s)
        return settle + self.walk_um(t)
