"""`focustrack bench phase`'s speed run: the filter on 21 planes of 2048 x 2048, one core.

Both updates of `focustrack_phase.acekf.reconstruct` on the same stack (Poisson noise at
100 photons, z from -5 to 5 um), in wall time and in the process's CPU time (which a
machine shared with other jobs stretches far less), beside the CPU time of the FFTs that
update's loop calls, run alone on the same size: the floor no element-wise work can take
the filter under. And the filter's peak memory (tracemalloc, on 512 x 512) in images of
complex64 (8 bytes a pixel), besides the stack.
"""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np

from focustrack_phase import acekf, transforms
from focustrack_phase.propagation import FoldedGrid

SPEED_PLANES = 21
MEMORY_SIZE_PX = 512


def update_ffts_cpu_s(update: acekf.Update, size_px: int, planes: int) -> float:
    """CPU seconds of the FFTs `reconstruct` calls with `update` on `planes` planes of
    size_px^2, alone (one worker), on working images padded as the filter's: per plane an
    inverse and a forward complex DFT (eqs. 30 and 33), ours also a real image filtered by
    the gain (a real forward DFT and two real inverses: the gain in the field's phase
    frame, its products in the packed spectrum included); then the inverse back at focus.
    Each transform is timed alone: the products between them are not counted."""
    rng = np.random.default_rng(1)
    shape = (size_px, size_px)
    field = transforms.padded_image(shape, np.complex64)
    field[...] = rng.normal(size=shape)
    residual = transforms.padded_image(shape, np.float32)
    imaginary = transforms.padded_image(shape, np.float32)
    grid = FoldedGrid(shape, 1.0)
    gain = np.full(grid.freq_sq_per_um2.shape, 1 / size_px**2, dtype=np.complex64)
    cpu_s = 0.0

    def timed(transform: Callable[..., object], *images: object) -> None:
        nonlocal cpu_s
        start_cpu = time.process_time()
        transform(*images)
        cpu_s += time.process_time() - start_cpu

    for _ in range(planes):
        timed(transforms.idft2, field)
        if update == "phase_frame":
            residual[...] = field.real
            timed(transforms.filter_real, residual, imaginary, gain, grid)
        timed(transforms.dft2, field)
        field *= np.float32(1 / size_px**2)  # keeps it finite, as the filter's products do
    timed(transforms.idft2, field)
    return cpu_s


def measure_speed(size_px: int) -> list[dict[str, Any]]:
    """Seconds for 21 planes of size_px^2 (one core), its FFTs' share and peak memory, per
    update."""
    rng = np.random.default_rng(0)
    z_um = np.linspace(-5.0, 5.0, SPEED_PLANES)
    stack = rng.poisson(100.0, size=(SPEED_PLANES, size_px, size_px)).astype(np.float32)
    small = stack[:, :MEMORY_SIZE_PX, :MEMORY_SIZE_PX].copy()
    rows = []
    updates: tuple[acekf.Update, ...] = ("phase_frame", "paper")
    for update in updates:
        options = acekf.AcekfOptions(update=update, background="none")  # the filter alone
        start, start_cpu = time.perf_counter(), time.process_time()
        acekf.reconstruct(stack, z_um, 0.532, 0.108, options=options)
        seconds, cpu_s = time.perf_counter() - start, time.process_time() - start_cpu
        fft_cpu_s = update_ffts_cpu_s(update, size_px, SPEED_PLANES)
        tracemalloc.start()
        acekf.reconstruct(small, z_um, 0.532, 0.108, options=options)
        peak_bytes = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        image_bytes = 8 * small.shape[1] * small.shape[2]
        rows.append(
            {"update": update, "planes": SPEED_PLANES, "size_px": size_px, "time_s": seconds,
             "cpu_s": cpu_s, "fft_cpu_s": fft_cpu_s,
             "peak_memory_images": peak_bytes / image_bytes}
        )  # fmt: skip
    return rows
