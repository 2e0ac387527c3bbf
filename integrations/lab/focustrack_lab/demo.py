"""A microscope in pure Python for pymmcore-plus: try the engine without hardware (extra `mmcore`).

`scope_core(scope)` (from `focustrack_core.mm_devices`) is a pymmcore-plus `UniMMCore`
with three Python devices, a camera ("Camera"), an XY stage ("XY") and a focus stage
("Z"), backed by any `Scope` (where the stages are, and the frame the camera sees
there). `DemoScope`
is a small synthetic one, numpy and scipy only: a textured specimen whose focus
follows a tilted, gently curved surface, blurred in proportion to the defocus,
with photon noise. FocusTrack's own simulated microscope backs the same devices
in the umbrella (`focustrack/lab_sim.py`) and in the instrument service
(`--backend mmcore-sim`).

Stage coordinates are useq's: x grows to the right, y upwards (a `GridRowsColumns`
puts row 0 at the top), all in um.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from focustrack_core.mm_devices import Scope, scope_core

__all__ = ["DemoScope", "Scope", "scope_core"]


@dataclass
class DemoScope:
    """A synthetic specimen under a microscope (module docstring); counts the frames snapped.

    The true focus at stage (x, y) um is `focus_um`: a tilt of `tilt_um_per_mm` (x, y)
    plus a bowl `bowl_um` deep at 1 mm from the origin. A frame at height z is the
    specimen's texture at that field of view, blurred by a Gaussian of
    `blur_px_per_um` px per um of defocus (and its own texture scale in focus), with
    photon noise at `photons` per pixel at mean brightness.
    """

    shape: tuple[int, int] = (256, 256)
    pixel_um: float = 0.5
    dof_um: float = 1.0
    tilt_um_per_mm: tuple[float, float] = (4.0, -3.0)
    bowl_um: float = 2.0
    blur_px_per_um: float = 2.0
    photons: float = 1000.0
    seed: int = 0
    x_um: float = 0.0
    y_um: float = 0.0
    z_um: float = 0.0
    exposure_ms: float = 10.0
    n_frames: int = 0

    @property
    def fov_um(self) -> tuple[float, float]:
        """The camera's field of view, (width, height) um: the MDA grid's fov_width, fov_height."""
        height, width = self.shape
        return width * self.pixel_um, height * self.pixel_um

    def focus_um(self, x_um: float, y_um: float) -> float:
        """The specimen's true focus height at stage (x, y), um (evaluation only)."""
        tilt_x, tilt_y = self.tilt_um_per_mm
        return (tilt_x * x_um + tilt_y * y_um) / 1e3 + self.bowl_um * (x_um**2 + y_um**2) / 1e6

    def frame(self) -> np.ndarray:
        """The camera frame (height, width) uint16 at the stages' position."""
        from scipy.ndimage import gaussian_filter  # as the focus maths: on first use

        defocus_um = abs(self.z_um - self.focus_um(self.x_um, self.y_um))
        image = _texture(self.shape, self.seed, round(self.x_um), round(self.y_um))
        if defocus_um > 0:
            image = gaussian_filter(image, self.blur_px_per_um * defocus_um, mode="reflect")
        rng = np.random.default_rng([self.seed, self.n_frames])
        self.n_frames += 1
        counts = rng.poisson(self.photons * image)
        return np.clip(counts, 0, np.iinfo(np.uint16).max).astype(np.uint16)


@functools.lru_cache(maxsize=64)
def _texture(shape: tuple[int, int], seed: int, x_um: int, y_um: int) -> np.ndarray:
    """The in-focus specimen at a stage position: (height, width) float64 of mean 1,
    blobs of a few px; cached, since a position is snapped many times."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng([seed, x_um & 0xFFFFFFFF, y_um & 0xFFFFFFFF])
    field = gaussian_filter(rng.standard_normal(shape), 2.0, mode="wrap")
    texture = np.clip(1.0 + 0.5 * field / field.std(), 0.05, None)
    texture.setflags(write=False)  # shared by every later call for this position
    return texture
