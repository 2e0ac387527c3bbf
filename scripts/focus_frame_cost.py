"""The focus maths' cost per frame with each image-filter backend (docs/benchmarks.md).

    .venv/bin/python scripts/focus_frame_cost.py

Times `focus_stack` (default settings; CPU time of the process, all its threads, so
other jobs on the machine move it little) on 11-frame stacks of 512x512 and 2048x2048
uint16 frames, best of 5, and prints ms per frame for OpenCV (the service's) and for
numpy/scipy (a lab install without OpenCV).
"""

from __future__ import annotations

import time

import numpy as np

from focustrack_focus import filters
from focustrack_focus.pipeline import FocusSettings, focus_stack

N_FRAMES = 11
REPEATS = 5


def ms_per_frame(size_px: int) -> float:
    """Best wall time of `focus_stack` over REPEATS runs, per frame, in ms."""
    field = np.random.default_rng(0).integers(500, 3500, (size_px, size_px), dtype=np.uint16)
    stack = np.stack([field] * N_FRAMES)
    z_um = np.linspace(-5.0, 5.0, N_FRAMES)
    settings = FocusSettings()
    focus_stack(stack, z_um, settings)  # first call: scipy's imports, the noise gain's cache
    best_s = np.inf
    for _ in range(REPEATS):
        started_s = time.process_time()
        focus_stack(stack, z_um, settings)
        best_s = min(best_s, time.process_time() - started_s)
    return 1e3 * best_s / N_FRAMES


def main() -> int:
    for backend in (filters.BACKEND, filters.ScipyFilters()):
        filters.BACKEND = backend
        costs = ", ".join(f"{size}x{size} {ms_per_frame(size):.2f} ms" for size in (512, 2048))
        print(f"{backend.name}: {costs} per frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
