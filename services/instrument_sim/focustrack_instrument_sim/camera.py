"""The camera: photon shot noise, read noise, full well, gain, offset and bit depth.

Shot noise is Poisson. Above `exact_poisson_below_e` electrons (every brightfield
frame at a usable exposure: thousands per pixel) it is drawn as its normal
approximation, mean = variance = signal, from a bank of standard normals read at a
random offset per plane: drawing 3 million fresh normals per frame would cost more
than rendering it. Pixels within a plane stay independent (consecutive bank
entries are), and so do planes (offsets differ). Dim planes get exact Poisson draws.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Camera:
    """A 12-bit scientific CMOS camera behind RGB filters (all values per pixel and channel).

    `background_e_per_s` is the signal through empty glass (transmission 1), so the
    signal of a frame is transmission x background_e_per_s x exposure_s. At the
    default exposure (TimingModel, 10 ms) the background fills 60% of the well.
    """

    bit_depth: int = 12
    gain_e_per_adu: float = 5.0
    offset_adu: float = 100.0
    read_noise_e: float = 2.0
    full_well_e: float = 20_000.0
    background_e_per_s: float = 1.2e6
    exact_poisson_below_e: float = 100.0

    def __post_init__(self) -> None:
        if not 1 <= self.bit_depth <= 16:
            raise ValueError(f"bit depth must be 1..16 (uint16 frames), got {self.bit_depth}")
        if min(self.gain_e_per_adu, self.full_well_e, self.background_e_per_s) <= 0:
            raise ValueError("gain, full well and background signal must be positive")
        if self.read_noise_e < 0 or self.offset_adu < 0:
            raise ValueError("read noise and offset must not be negative")

    @property
    def saturation_adu(self) -> int:
        """The highest value a pixel reads: a full well, or the top of the bit depth."""
        full_well_adu = int(self.full_well_e / self.gain_e_per_adu + self.offset_adu)
        return min(2**self.bit_depth - 1, full_well_adu)


class NoiseBank:
    """Standard normal float32 samples, handed out as (height, width) views at random offsets."""

    def __init__(self, shape: tuple[int, int], rng: np.random.Generator) -> None:
        self.shape = shape
        self._size = shape[0] * shape[1]
        self._samples = rng.standard_normal(2 * self._size, dtype=np.float32)

    def plane(self, rng: np.random.Generator) -> np.ndarray:
        start = int(rng.integers(0, self._size + 1))
        return self._samples[start : start + self._size].reshape(self.shape)


def expose(
    camera: Camera,
    signal_e: np.ndarray,
    rng: np.random.Generator,
    bank: NoiseBank,
    out: np.ndarray | None = None,
    scratch: np.ndarray | None = None,
) -> np.ndarray:
    """The digitised frame, (height, width) uint16, of the mean signal `signal_e` (e-, float32).

    Electrons beyond the full well and ADUs beyond the bit depth saturate. With `out`
    (uint16) and `scratch` (float32, the shape of `signal_e`) the frame is written into
    `out`, `signal_e` is overwritten, and nothing is allocated (see `optics.blurred`).
    """
    in_place = out is not None and scratch is not None
    signal_e = cv2.max(signal_e, 0.0, dst=signal_e if in_place else None)  # FFT round-off < 0
    if cv2.minMaxLoc(signal_e)[1] < camera.exact_poisson_below_e:
        electrons = rng.poisson(signal_e).astype(np.float32)
        electrons += camera.read_noise_e * rng.standard_normal(signal_e.shape, dtype=np.float32)
    else:
        sigma_e = cv2.sqrt(cv2.add(signal_e, camera.read_noise_e**2, dst=scratch), dst=scratch)
        noise_e = cv2.multiply(sigma_e, bank.plane(rng), dst=scratch)
        electrons = cv2.add(signal_e, noise_e, dst=signal_e if in_place else None)
    # ADU = electrons / gain + offset, rounded and saturated at 0 by OpenCV's cast to uint16;
    # the full well (in ADU) and the bit depth cap it from above.
    adu = cv2.addWeighted(
        electrons,
        1.0 / camera.gain_e_per_adu,
        electrons,
        0.0,
        camera.offset_adu,
        dst=out,
        dtype=cv2.CV_16U,
    )
    return cv2.min(adu, camera.saturation_adu, dst=adu)
