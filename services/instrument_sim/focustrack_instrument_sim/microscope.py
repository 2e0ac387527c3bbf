"""The simulated microscope: slides, a renderer (optics + camera) and a stage, without any I/O.

`Microscope.acquire` validates a request, moves the stage, and renders the z-stack
of the tile: for each frame, the defocus is the frame's z minus the tile's true
focus (plus the stage's z drift at that moment), the in-focus spectrum of the tile
(cached) is multiplied by the OTF of that defocus, and the camera digitises the
result. The service (`service.py`) puts this on Zenoh.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import cv2
import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_instrument_sim import optics as opt
from focustrack_instrument_sim.camera import Camera, NoiseBank, expose
from focustrack_instrument_sim.specimen import SpecimenSpec, blood_smear, dust_layer
from focustrack_instrument_sim.stage import StackTiming, Stage, StageSpec
from focustrack_instrument_sim.surfaces import SurfaceSpec, generate_surfaces, load_map

#: (seed, (height, width), pixel size in um) -> transmission (height, width, 3) float32
SpecimenFn = Callable[[np.random.SeedSequence, tuple[int, int], float], np.ndarray]


class Refusal(StrEnum):
    """Why a request cannot be acquired."""

    MALFORMED = "malformed_request"
    UNKNOWN_SLIDE = "unknown_slide"
    TILE_OUTSIDE_SLIDE = "tile_outside_slide"
    Z_OUT_OF_RANGE = "z_out_of_range"
    TOO_MANY_FRAMES = "too_many_frames"


class AcquisitionRefusedError(ValueError):
    """A request the microscope will not carry out; `reason` and `field` say why."""

    def __init__(self, reason: Refusal, message: str, field: str = "") -> None:
        super().__init__(message)
        self.reason = reason
        self.field = field


@dataclass(frozen=True)
class Slide:
    """A slide: its true focus surface z*(row, col) in um, its tile grid and its specimen's seed."""

    name: str
    focus_um: np.ndarray
    grid: ScanGrid
    specimen_seed: tuple[int, ...]

    def __post_init__(self) -> None:
        if self.focus_um.shape != self.grid.shape:
            raise ValueError(f"surface {self.focus_um.shape} does not match grid {self.grid.shape}")


def slides_from_seed(
    seed: int, n_slides: int, spec: SurfaceSpec, pitch_um: float = 200.0
) -> list[Slide]:
    """`n_slides` generated slides named slide-0, slide-1, ...

    Slide i has the surface `generate_surfaces(spec, n_slides, seed)[i]`, the
    same map the accuracy benchmark draws for that seed and index.
    """
    surfaces = generate_surfaces(spec, n_slides, seed)
    grid = ScanGrid(spec.rows, spec.cols, pitch_um)
    return [Slide(f"slide-{i}", surface, grid, (seed, i)) for i, surface in enumerate(surfaces)]


def slides_from_map(path: str | Path, seed: int, pitch_um: float = 200.0) -> list[Slide]:
    """Slides whose true focus comes from a user's map file (one slide per map in it)."""
    maps = load_map(path)
    maps = maps[None] if maps.ndim == 2 else maps
    grid = ScanGrid(maps.shape[1], maps.shape[2], pitch_um)
    return [Slide(f"slide-{i}", surface, grid, (seed, i)) for i, surface in enumerate(maps)]


@dataclass(frozen=True)
class MicroscopeSpec:
    """Everything about the instrument except its slides (lengths in um)."""

    optics: opt.Optics = field(default_factory=opt.Optics)
    camera: Camera = field(default_factory=Camera)
    stage: StageSpec = field(default_factory=StageSpec)
    specimen: SpecimenSpec = field(default_factory=SpecimenSpec)
    height: int = 1024
    width: int = 1024
    max_frames: int = 64
    dust_dz_um: float = 8.0  # height of the dust plane above the specimen
    cached_tiles: int = 8  # in-focus spectra kept (12 MB each at 1024 x 1024)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)


@dataclass(frozen=True)
class TileSpectra:
    """CCS spectra of a tile's in-focus transmission, one per channel, pixel MTF applied."""

    channels: tuple[np.ndarray, ...]
    dust: np.ndarray | None


class Renderer:
    """Optics and camera at one frame size: tile transmission in, digitised z-stack out."""

    def __init__(self, spec: MicroscopeSpec, rng: np.random.Generator) -> None:
        self.spec = spec
        geometry = opt.FrameGeometry(spec.height, spec.width, spec.optics.pixel_size_um)
        self._pixel_mtf = geometry.pixel_mtf
        self._otfs = [opt.DefocusOTF(spec.optics, wl) for wl in spec.optics.wavelengths_um]
        self._bins = [geometry.bins(otf).astype(np.int32) for otf in self._otfs]
        self._bank = NoiseBank(spec.shape, rng)

    def spectra(self, transmission: np.ndarray, dust: np.ndarray | None) -> TileSpectra:
        """Spectra of a tile (transmission (height, width, 3)) and its dust layer, if any."""
        channels = tuple(
            opt.spectrum(transmission[..., c]) * self._pixel_mtf for c in range(len(opt.CHANNELS))
        )
        return TileSpectra(channels, None if dust is None else opt.spectrum(dust) * self._pixel_mtf)

    def render(
        self, tile: TileSpectra, dz_um: np.ndarray, exposure_s: float, rng: np.random.Generator
    ) -> np.ndarray:
        """The z-stack at defocus `dz_um` (frame z - true focus), (n, height, width, 3) uint16."""
        camera = self.spec.camera
        signal_e = camera.background_e_per_s * exposure_s
        pixels = np.empty((len(dz_um), *self.spec.shape, len(opt.CHANNELS)), dtype=np.uint16)
        for k, dz in enumerate(dz_um):
            dust = None
            if tile.dust is not None:  # the dust plane sits dust_dz_um above the specimen
                dz_dust = dz - self.spec.dust_dz_um
                dust = opt.blurred(
                    tile.dust, self._otfs[1].profile(dz_dust).take(self._bins[1]), 1.0
                )
            planes = []
            for c, (otf, bins) in enumerate(zip(self._otfs, self._bins, strict=True)):
                plane = opt.blurred(tile.channels[c], otf.profile(dz).take(bins), signal_e)
                if dust is not None:
                    plane *= dust
                planes.append(expose(camera, plane, rng, self._bank))
            cv2.merge(planes, dst=pixels[k])
        return pixels


@dataclass(frozen=True)
class Stack:
    """An acquired z-stack and what it cost."""

    slide: str
    row: int
    col: int
    z_um: np.ndarray  # (n,) commanded z of every frame
    pixels: np.ndarray  # (n, height, width, 3) uint16, RGB
    exposure_s: float
    stage_x_um: float
    stage_y_um: float
    timing: StackTiming
    clock_s: float  # simulated clock when the stack was complete


class Microscope:
    """Slides on a stage under a simulated objective and camera."""

    def __init__(
        self,
        slides: Sequence[Slide],
        spec: MicroscopeSpec | None = None,
        *,
        seed: int = 0,
        specimen: SpecimenFn | None = None,
    ) -> None:
        self.spec = spec or MicroscopeSpec()
        if len({slide.name for slide in slides}) != len(slides):
            raise ValueError("slide names must be unique")
        self.slides = {slide.name: slide for slide in slides}
        self.stage = Stage(self.spec.stage)
        self._rng = np.random.default_rng([seed, 1])
        self.renderer = Renderer(self.spec, self._rng)
        self._specimen = specimen or functools.partial(blood_smear, self.spec.specimen)
        self._tiles: OrderedDict[tuple[str, int, int], TileSpectra] = OrderedDict()

    @property
    def pixel_size_um(self) -> float:
        return self.spec.optics.pixel_size_um

    def check(
        self,
        slide: str,
        row: int,
        col: int,
        z_low_um: float,
        z_step_um: float,
        n_frames: int,
        exposure_s: float,
    ) -> Slide:
        """The slide of a request, or AcquisitionRefusedError saying what is wrong with it."""
        if slide not in self.slides:
            known = ", ".join(sorted(self.slides))
            raise AcquisitionRefusedError(
                Refusal.UNKNOWN_SLIDE, f"unknown slide {slide!r}; known: {known}", "slide"
            )
        grid = self.slides[slide].grid
        if not grid.contains(row, col):
            raise AcquisitionRefusedError(
                Refusal.TILE_OUTSIDE_SLIDE,
                f"tile ({row}, {col}) is outside slide {slide!r} of {grid.rows}x{grid.cols} tiles",
                "row" if not 0 <= row < grid.rows else "col",
            )
        if n_frames > self.spec.max_frames:
            raise AcquisitionRefusedError(
                Refusal.TOO_MANY_FRAMES,
                f"{n_frames} frames requested; the instrument takes at most {self.spec.max_frames}",
                "n_frames",
            )
        if n_frames < 1:
            raise AcquisitionRefusedError(
                Refusal.MALFORMED, f"n_frames must be at least 1, got {n_frames}", "n_frames"
            )
        if not np.isfinite(z_low_um):
            raise AcquisitionRefusedError(Refusal.MALFORMED, "z_low_um must be finite", "z_low_um")
        if n_frames > 1 and not (np.isfinite(z_step_um) and z_step_um > 0):
            raise AcquisitionRefusedError(
                Refusal.MALFORMED,
                f"z_step_um must be positive for {n_frames} frames, got {z_step_um}",
                "z_step_um",
            )
        z_high_um = z_low_um + (n_frames - 1) * z_step_um
        z_low, z_high = self.spec.stage.z_range_um
        if z_low_um < z_low or z_high_um > z_high:
            raise AcquisitionRefusedError(
                Refusal.Z_OUT_OF_RANGE,
                f"frames span z {z_low_um:.3f}..{z_high_um:.3f} um, outside the stage's travel "
                f"{z_low:.1f}..{z_high:.1f} um",
                "z_low_um",
            )
        if not (np.isfinite(exposure_s) and 0 < exposure_s <= 10.0):
            raise AcquisitionRefusedError(
                Refusal.MALFORMED, f"exposure must be in (0, 10] s, got {exposure_s}", "exposure_s"
            )
        x_um, y_um = grid.stage_xy_um(row, col)
        (x_low, x_high), (y_low, y_high) = self.spec.stage.x_range_um, self.spec.stage.y_range_um
        if not (x_low <= x_um <= x_high and y_low <= y_um <= y_high):
            raise AcquisitionRefusedError(
                Refusal.TILE_OUTSIDE_SLIDE,
                f"tile ({row}, {col}) at ({x_um:.0f}, {y_um:.0f}) um is beyond the stage's travel",
                "row",
            )
        return self.slides[slide]

    def acquire(
        self,
        slide: str,
        row: int,
        col: int,
        z_low_um: float,
        z_step_um: float,
        n_frames: int,
        exposure_s: float | None = None,
    ) -> Stack:
        """Frames at z_low_um, z_low_um + z_step_um, ... (um) of tile (row, col) of `slide`.

        `exposure_s` defaults to the timing model's. Raises AcquisitionRefusedError.
        """
        exposure_s = self.spec.stage.timing.exposure_s if exposure_s is None else exposure_s
        chosen = self.check(slide, row, col, z_low_um, z_step_um, n_frames, exposure_s)
        z_um = z_low_um + z_step_um * np.arange(n_frames)
        x_um, y_um = chosen.grid.stage_xy_um(row, col)
        tile = self._tile_spectra(chosen, row, col)
        timing, frame_times_s = self.stage.acquire(x_um, y_um, n_frames, exposure_s)
        focus_um = chosen.focus_um[row, col] + self.stage.drift_um(frame_times_s)
        pixels = self.renderer.render(tile, z_um - focus_um, exposure_s, self._rng)
        return Stack(
            slide, row, col, z_um, pixels, exposure_s, x_um, y_um, timing, self.stage.clock_s
        )

    def truth_um(self, slide: str) -> tuple[np.ndarray, float]:
        """(true focus of every tile now, drift included, (rows, cols) um; the drift in um)."""
        drift_um = self.stage.drift_um(self.stage.clock_s)
        return self.slides[slide].focus_um + drift_um, drift_um

    def _tile_spectra(self, slide: Slide, row: int, col: int) -> TileSpectra:
        key = (slide.name, row, col)
        if key in self._tiles:
            self._tiles.move_to_end(key)
            return self._tiles[key]
        seed = np.random.SeedSequence([*slide.specimen_seed, row, col])
        specimen_seed, dust_seed = seed.spawn(2)
        transmission = self._specimen(specimen_seed, self.spec.shape, self.pixel_size_um)
        dust = None
        if self.spec.specimen.dust_density > 0:
            dust = dust_layer(self.spec.specimen, dust_seed, self.spec.shape, self.pixel_size_um)
        tile = self.renderer.spectra(transmission, dust)
        self._tiles[key] = tile
        while len(self._tiles) > self.spec.cached_tiles:
            self._tiles.popitem(last=False)
        return tile
