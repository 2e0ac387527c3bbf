"""The simulated microscope: slides, a renderer (optics + camera) and a stage, without any I/O.

`Microscope.plan` validates a request and moves the stage; `Microscope.render` then
renders the frames of the z-stack, in order, each as soon as it is done: for each
frame, the defocus is the frame's z minus the tile's true focus (plus the stage's z
drift at that moment), the in-focus spectrum of the tile (cached, as many tiles as
`MicroscopeSpec.cache_mb` holds) is multiplied by the OTF of that defocus, and the
camera digitises the result. A phase specimen (`MicroscopeSpec.specimen_kind`: unstained
cells, `phase_specimen`) is imaged with partially coherent light instead
(`optics.AbbeImager`: its cached spectrum, one inverse FFT per source point), at one
wavelength: its frames are monochrome, the same counts in every channel. Frames render
on `MicroscopeSpec.workers` threads (OpenCV and numpy release the GIL), each with a
random generator of its own drawn in frame order, so a stack is the same whichever
thread renders which frame. `acquire` does both at once; `true_phase` gives a tile's
true phase (evaluation only). `simulated.SimulatedInstrument` serves it as an
`instrument.Instrument`.
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces, load_map
from focustrack_instrument_sim import optics as opt
from focustrack_instrument_sim.camera import Camera, NoiseBank, expose
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    FrameFormat,
    Frames,
    ImagingConditions,
    Purpose,
    Refusal,
    StackPlan,
    StackRequest,
    StackTiming,
    TilePhase,
    check_request,
    check_tile,
)
from focustrack_instrument_sim.phase_specimen import (
    GLASS_PHASE_RAD,
    PhaseObject,
    PhaseSpecimenSpec,
    cell_culture,
    red_cells,
)
from focustrack_instrument_sim.simulator_options import SPECIMENS, default
from focustrack_instrument_sim.specimen import SpecimenSpec, blood_smear, dust_layer
from focustrack_instrument_sim.stage import Stage, StageSpec

#: (seed, (height, width), pixel size in um) -> a tile's specimen: an absorbing one's
#: transmission (height, width, 3) float32 in (0, 1], or a `PhaseObject`.
SpecimenFn = Callable[[np.random.SeedSequence, tuple[int, int], float], np.ndarray | PhaseObject]


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
    seed: int, n_slides: int, spec: SurfaceSpec, pitch_um: float = default("pitch_um")
) -> list[Slide]:
    """`n_slides` generated slides named slide-0, slide-1, ...

    Slide i has the surface `generate_surfaces(spec, n_slides, seed)[i]`, the
    same map the accuracy benchmark draws for that seed and index.
    """
    surfaces = generate_surfaces(spec, n_slides, seed)
    grid = ScanGrid(spec.rows, spec.cols, pitch_um)
    return [Slide(f"slide-{i}", surface, grid, (seed, i)) for i, surface in enumerate(surfaces)]


def slides_from_map(
    path: str | Path, seed: int, pitch_um: float = default("pitch_um")
) -> list[Slide]:
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
    # one of simulator_options.SPECIMENS; it also says how the stack headers describe the
    # imaging (`imaging`), also for a `Microscope` given a specimen function of its own
    specimen_kind: str = default("specimen")
    phase_specimen: PhaseSpecimenSpec = field(default_factory=PhaseSpecimenSpec)
    illumination: opt.Illumination = field(default_factory=opt.Illumination)  # phase specimens'
    height: int = default("height")
    width: int = default("width")
    max_frames: int = default("max_frames")
    dust_dz_um: float = 8.0  # height of the dust plane above the specimen
    # in-focus spectra kept, MB: 16.8 MB a tile at 1024 x 1024, 4.2 at 512
    cache_mb: float = default("cache_mb")
    cached_tiles: int | None = None  # a fixed number of tiles instead of what cache_mb holds
    workers: int = default("workers")  # threads rendering the frames of a stack

    def __post_init__(self) -> None:
        opt.check_frame_shape(self.shape)  # now, not when the renderer is made for a stack
        if self.specimen_kind not in SPECIMENS:
            raise ValueError(f"specimen must be one of {', '.join(SPECIMENS)}")
        if self.illumination.condenser_na > self.optics.numerical_aperture:
            raise ValueError(
                f"the condenser NA ({self.illumination.condenser_na}) must not exceed the "
                f"objective's ({self.optics.numerical_aperture}): that would be darkfield"
            )

    @property
    def phase_imaging(self) -> bool:
        """Whether the specimen is a phase specimen, imaged with partially coherent light."""
        return self.specimen_kind != "stained-smear"

    @property
    def imaging(self) -> ImagingConditions:
        """How the frames are formed, for the stack headers. A stained smear is imaged
        incoherently (the condenser filled to the objective's NA) at the camera's green
        wavelength; a phase specimen with `illumination`. Gain and offset are the camera's
        (photons per count: electrons per count at a quantum efficiency of 1)."""
        if self.phase_imaging:
            wavelength_um, condenser_na = (
                self.illumination.wavelength_um,
                self.illumination.condenser_na,
            )
        else:
            wavelength_um = self.optics.reference_wavelength_um
            condenser_na = self.optics.numerical_aperture
        return ImagingConditions(
            wavelength_um=wavelength_um,
            condenser_na=condenser_na,
            objective_na=self.optics.numerical_aperture,
            photons_per_count=self.camera.gain_e_per_adu,
            dark_counts=self.camera.offset_adu,
        )

    @property
    def tiles_cached(self) -> int:
        """How many tiles' spectra the cache keeps (float32, three channels and dust)."""
        if self.cached_tiles is not None:
            return self.cached_tiles
        tile_bytes = 4 * self.height * self.width * (len(opt.CHANNELS) + 1)
        return max(1, int(self.cache_mb * 1e6 // tile_bytes))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def frame(self) -> FrameFormat:
        """A frame: (height, width, 3) uint16, RGB, the camera's bit depth."""
        return FrameFormat(
            self.height, self.width, opt.CHANNELS, np.dtype(np.uint16), self.camera.bit_depth
        )


@dataclass(frozen=True)
class TileSpectra:
    """CCS spectra of a tile's in-focus transmission, one per channel, pixel MTF applied,
    and of its dust layer (or None). A virtual slide's tile (`virtual_slide`) says how high
    its dust lies above it (um; None: `MicroscopeSpec.dust_dz_um`), and may carry a fold:
    a second layer's spectra, one per channel, `fold_dz_um` above the first."""

    channels: tuple[np.ndarray, ...]
    dust: np.ndarray | None
    dust_dz_um: float | None = None
    fold: tuple[np.ndarray, ...] | None = None
    fold_dz_um: float = 0.0


@dataclass(frozen=True)
class PhaseTileSpectrum:
    """The spectrum of a phase specimen's complex transmittance (`optics.AbbeImager`),
    complex64 (height, width), and the CCS spectrum of its dust layer (or None)."""

    transmittance: np.ndarray
    dust: np.ndarray | None


class Renderer:
    """Optics and camera at one frame size: tile transmission in, digitised z-stack out."""

    def __init__(self, spec: MicroscopeSpec, rng: np.random.Generator) -> None:
        self.spec = spec
        geometry = opt.FrameGeometry(spec.height, spec.width, spec.optics.pixel_size_um)
        self._pixel_mtf = geometry.pixel_mtf
        self._otfs = [opt.DefocusOTF(spec.optics, wl) for wl in spec.optics.wavelengths_um]
        self._bins = [geometry.bins(otf) for otf in self._otfs]  # intp: what take() wants
        self._bank = NoiseBank(spec.shape, rng)
        self._local = threading.local()  # each rendering thread's _Workspace

    @functools.cached_property
    def abbe(self) -> opt.AbbeImager:
        """The partially coherent imaging of phase specimens, made for the first one."""
        return opt.AbbeImager(self.spec.optics, self.spec.illumination, self.spec.shape)

    def spectra(
        self, specimen: np.ndarray | PhaseObject, dust: np.ndarray | None
    ) -> TileSpectra | PhaseTileSpectrum:
        """Spectra of a tile (an absorbing specimen's transmission (height, width, 3), or a
        phase specimen) and its dust layer, if any."""
        dust_spectrum = None if dust is None else opt.spectrum(dust) * self._pixel_mtf
        if isinstance(specimen, PhaseObject):
            wavelength_um = self.spec.illumination.wavelength_um
            return PhaseTileSpectrum(
                self.abbe.spectrum(specimen.transmittance(wavelength_um)), dust_spectrum
            )
        channels = tuple(
            opt.spectrum(specimen[..., c]) * self._pixel_mtf for c in range(len(opt.CHANNELS))
        )
        return TileSpectra(channels, dust_spectrum)

    def render_frame(
        self,
        tile: TileSpectra | PhaseTileSpectrum,
        dz_um: float,
        exposure_s: float,
        rng: np.random.Generator,
        out: np.ndarray,
    ) -> np.ndarray:
        """The frame at defocus `dz_um` (frame z - true focus), into `out` (height, width, 3)
        uint16, which it returns. Thread-safe: the renderer's own state is only read, and
        each thread works in buffers of its own."""
        camera = self.spec.camera
        signal_e = camera.background_e_per_s * exposure_s
        work = self._workspace()
        dust = None
        if tile.dust is not None:  # the dust plane sits dust_dz_um above the specimen
            above_um = getattr(tile, "dust_dz_um", None)
            dz_dust = dz_um - (self.spec.dust_dz_um if above_um is None else above_um)
            otf_map = self._otfs[1].profile(dz_dust).take(self._bins[1], out=work.otf_map)
            dust = opt.blurred(tile.dust, otf_map, 1.0, out=work.dust)
        if isinstance(tile, PhaseTileSpectrum):
            if work.abbe is None:
                work.abbe = self.abbe.workspace()
            plane = self.abbe.intensity(tile.transmittance, dz_um, work.abbe, out=work.plane)
            plane *= np.float32(signal_e)
            if dust is not None:
                plane *= dust
            mono = expose(camera, plane, rng, self._bank, out=work.adu[0], scratch=work.scratch)
            return cv2.merge([mono] * len(opt.CHANNELS), dst=out)  # one wavelength: monochrome
        for c, (otf, bins) in enumerate(zip(self._otfs, self._bins, strict=True)):
            otf_map = otf.profile(dz_um).take(bins, out=work.otf_map)
            plane = opt.blurred(tile.channels[c], otf_map, signal_e, out=work.plane)
            if tile.fold is not None:  # a fold's upper layer, at its own defocus
                fold_map = otf.profile(dz_um - tile.fold_dz_um).take(bins, out=work.otf_map)
                plane *= opt.blurred(tile.fold[c], fold_map, 1.0, out=work.fold)
            if dust is not None:
                plane *= dust
            expose(camera, plane, rng, self._bank, out=work.adu[c], scratch=work.scratch)
        cv2.merge(work.adu, dst=out)
        return out

    def _workspace(self) -> _Workspace:
        work: _Workspace | None = getattr(self._local, "work", None)
        if work is None:
            work = self._local.work = _Workspace(self.spec.shape, len(opt.CHANNELS))
        return work


class _Workspace:
    """One rendering thread's buffers, reused frame after frame: allocating fresh megabyte
    arrays for every step cost more in page faults than the FFTs themselves."""

    def __init__(self, shape: tuple[int, int], channels: int) -> None:
        self.otf_map = np.empty(shape, dtype=np.float32)
        self.plane = np.empty(shape, dtype=np.float32)
        self.dust = np.empty(shape, dtype=np.float32)
        self.fold = np.empty(shape, dtype=np.float32)
        self.scratch = np.empty(shape, dtype=np.float32)
        self.adu = tuple(np.empty(shape, dtype=np.uint16) for _ in range(channels))
        self.abbe: opt.AbbeWorkspace | None = None  # made for the first phase specimen


@dataclass(frozen=True)
class SimulatedPlan(StackPlan):
    """An accepted acquisition: the stage has moved (and the simulated clock with it);
    its frames are still to be rendered.

    dz_um (n,): every frame's defocus from the true focus, um; rngs: one random
    generator per frame; tile: the in-focus spectra of the tile.
    """

    dz_um: np.ndarray
    rngs: tuple[np.random.Generator, ...]
    tile: TileSpectra | PhaseTileSpectrum


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
        seed: int = default("seed"),
        specimen: SpecimenFn | None = None,
    ) -> None:
        self.spec = spec or MicroscopeSpec()
        if len({slide.name for slide in slides}) != len(slides):
            raise ValueError("slide names must be unique")
        self.slides = {slide.name: slide for slide in slides}
        self.stage = Stage(self.spec.stage)
        self._rng = np.random.default_rng([seed, 1])
        self._pool = ThreadPoolExecutor(self.spec.workers, thread_name_prefix="render")
        self._specimen = specimen or specimen_function(self.spec)
        #: (slide, row, col, view y um, view x um) -> the tile's spectra
        self._tiles: OrderedDict[
            tuple[str, int, int, float, float], TileSpectra | PhaseTileSpectrum
        ] = OrderedDict()

    @functools.cached_property
    def renderer(self) -> Renderer:
        """Optics and camera, made when the first stack is planned (on the acquiring
        thread): building them, and importing scipy, takes a fraction of a second that the
        instrument's description (the service's info) does not wait for."""
        return Renderer(self.spec, self._rng)

    @property
    def pixel_size_um(self) -> float:
        return self.spec.optics.pixel_size_um

    def check(self, request: StackRequest, exposure_s: float) -> Slide:
        """The slide of a request, or AcquisitionRefusedError saying what is wrong with it
        (`instrument.check_request`, and a tile beyond the stage's XY travel)."""
        grids = {name: slide.grid for name, slide in self.slides.items()}
        grid = check_request(
            request, exposure_s, grids, self.spec.stage.z_range_um, self.spec.max_frames
        )
        row, col = request.row, request.col
        x_um, y_um = grid.stage_xy_um(row, col)
        x_um, y_um = x_um + request.stage_offset_x_um, y_um + request.stage_offset_y_um
        (x_low, x_high), (y_low, y_high) = self.spec.stage.x_range_um, self.spec.stage.y_range_um
        if not (x_low <= x_um <= x_high and y_low <= y_um <= y_high):
            raise AcquisitionRefusedError(
                Refusal.TILE_OUTSIDE_SLIDE,
                f"tile ({row}, {col}) at ({x_um:.0f}, {y_um:.0f}) um is beyond the stage's travel",
                "row",
            )
        return self.slides[request.slide]

    def plan(
        self,
        slide: str,
        row: int,
        col: int,
        z_low_um: float,
        z_step_um: float,
        n_frames: int,
        exposure_s: float | None = None,
        purpose: Purpose = Purpose.FOCUS,
        reference_z_um: float = 0.0,
        *,
        stage_offset_um: tuple[float, float] = (0.0, 0.0),
    ) -> SimulatedPlan:
        """Accept frames at z_low_um, z_low_um + z_step_um, ... (um) of tile (row, col) of
        `slide` and move the stage there, `stage_offset_um` (x, y) from the tile's place;
        `render` makes the frames.

        `exposure_s` defaults to the timing model's. `purpose` and `reference_z_um` (um, the
        objective z a PHASE stack is reconstructed at) go into the plan as they are; the
        frames are the same for either purpose. The frames show the slide where the stage
        went, less where the slide lies on it (`StageSpec.slide_offset_um`). Raises
        AcquisitionRefusedError.
        """
        exposure_s = self.spec.stage.timing.exposure_s if exposure_s is None else exposure_s
        request = StackRequest(
            slide, row, col, z_low_um, z_step_um, n_frames, exposure_s, purpose, reference_z_um,
            *stage_offset_um,
        )  # fmt: skip
        chosen = self.check(request, exposure_s)
        z_um = z_low_um + z_step_um * np.arange(n_frames)
        x_um, y_um = chosen.grid.stage_xy_um(row, col)
        x_um, y_um = x_um + stage_offset_um[0], y_um + stage_offset_um[1]
        slide_x_um, slide_y_um = self.spec.stage.slide_offset_um
        view_um = (stage_offset_um[1] - slide_y_um, stage_offset_um[0] - slide_x_um)
        tile = self._tile_spectra(chosen, row, col, view_um)
        timing, frame_times_s = self.stage.acquire(x_um, y_um, n_frames, exposure_s)
        focus_um = chosen.focus_um[row, col] + self.stage.drift_um(frame_times_s)
        return SimulatedPlan(
            slide=slide,
            row=row,
            col=col,
            stage_x_um=x_um,
            stage_y_um=y_um,
            z_um=z_um,
            exposure_s=exposure_s,
            frame=self.spec.frame,
            pixel_size_um=self.pixel_size_um,
            timing=timing,
            clock_s=self.stage.clock_s,
            dz_um=z_um - focus_um,
            rngs=tuple(self._rng.spawn(n_frames)),
            tile=tile,
            purpose=purpose,
            reference_z_um=reference_z_um,
            imaging=self.spec.imaging,
        )

    def render(self, plan: SimulatedPlan, out: Callable[[int], np.ndarray] | None = None) -> Frames:
        """The frames of `plan`, (height, width, 3) uint16 each, in order, each yielded as
        soon as it is rendered (the next ones are already under way on the pool).

        `out(k)` gives the array frame k is rendered into (default: a new array).
        """
        frame = self.spec.frame
        target = out or (lambda _: np.empty(frame.shape, dtype=frame.dtype))
        futures = [
            self._pool.submit(
                self.renderer.render_frame, plan.tile, dz, plan.exposure_s, rng, target(k)
            )
            for k, (dz, rng) in enumerate(zip(plan.dz_um, plan.rngs, strict=True))
        ]
        try:
            for future in futures:
                yield future.result()
        finally:  # a consumer that stops early leaves no work behind
            for future in futures:
                future.cancel()

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
        """`plan` and `render` at once: the whole stack (see `plan`)."""
        plan = self.plan(slide, row, col, z_low_um, z_step_um, n_frames, exposure_s)
        pixels = np.empty((n_frames, *self.spec.shape, len(opt.CHANNELS)), dtype=np.uint16)
        for _ in self.render(plan, pixels.__getitem__):
            pass
        return Stack(
            slide,
            row,
            col,
            plan.z_um,
            pixels,
            plan.exposure_s,
            plan.stage_x_um,
            plan.stage_y_um,
            plan.timing,
            plan.clock_s,
        )

    def close(self) -> None:
        """Stop the rendering threads."""
        self._pool.shutdown(cancel_futures=True)

    def truth_um(self, slide: str) -> tuple[np.ndarray, float]:
        """(true focus of every tile now, drift included, (rows, cols) um; the drift in um)."""
        drift_um = self.stage.drift_um(self.stage.clock_s)
        return self.slides[slide].focus_um + drift_um, drift_um

    def true_phase(self, slide: str, row: int, col: int) -> TilePhase:
        """The true phase of tile (row, col) of `slide` (radians, float32 (height, width),
        not wrapped) at the illumination's wavelength, and the tile's true focus now.

        The same specimen its frames show (drawn again from the tile's seed; dust is not
        part of it). A stained smear is modelled as a pure absorber: its phase is 0.
        AcquisitionRefusedError for an unknown slide or a tile outside it.
        """
        check_tile(slide, row, col, {name: s.grid for name, s in self.slides.items()})
        specimen_seed, _ = self._tile_seeds(self.slides[slide], row, col)
        specimen = self._specimen(specimen_seed, self.spec.shape, self.pixel_size_um)
        if isinstance(specimen, PhaseObject):
            phase_rad = specimen.phase_rad(self.spec.illumination.wavelength_um)
        else:
            phase_rad = np.zeros(self.spec.shape, dtype=np.float32)
        focus_um, _ = self.truth_um(slide)
        return TilePhase(phase_rad, self.pixel_size_um, float(focus_um[row, col]))

    def specimen_in_view(self, slide: str, row: int, col: int) -> bool:
        """Whether tile (row, col) of `slide` shows any specimen (evaluation only): a phase
        specimen's cells anywhere (a phase of `GLASS_PHASE_RAD` or more), a stained
        field's anything but plasma (a uniform transmission: the smear's empty fields).
        AcquisitionRefusedError for an unknown slide or a tile outside it."""
        check_tile(slide, row, col, {name: s.grid for name, s in self.slides.items()})
        specimen_seed, _ = self._tile_seeds(self.slides[slide], row, col)
        specimen = self._specimen(specimen_seed, self.spec.shape, self.pixel_size_um)
        if isinstance(specimen, PhaseObject):
            phase_rad = specimen.phase_rad(self.spec.illumination.wavelength_um)
            return bool(np.any(np.abs(phase_rad) >= GLASS_PHASE_RAD))
        return not np.all(specimen == specimen[0, 0])  # a pixel's every channel alike

    @staticmethod
    def _tile_seeds(
        slide: Slide, row: int, col: int
    ) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
        """The seeds of a tile's specimen and of its dust layer."""
        specimen_seed, dust_seed = np.random.SeedSequence([*slide.specimen_seed, row, col]).spawn(2)
        return specimen_seed, dust_seed

    def _tile_spectra(
        self, slide: Slide, row: int, col: int, view_um: tuple[float, float] = (0.0, 0.0)
    ) -> TileSpectra | PhaseTileSpectrum:
        """The spectra of tile (row, col) seen `view_um` (y, x) from its place on the slide."""
        view_um = (round(view_um[0], 4), round(view_um[1], 4))  # one key for one place
        key = (slide.name, row, col, *view_um)
        if key in self._tiles:
            self._tiles.move_to_end(key)
            return self._tiles[key]
        tile = self._new_tile_spectra(slide, row, col, view_um)
        self._tiles[key] = tile
        while len(self._tiles) > self.spec.tiles_cached:
            self._tiles.popitem(last=False)
        return tile

    def _new_tile_spectra(
        self, slide: Slide, row: int, col: int, view_um: tuple[float, float]
    ) -> TileSpectra | PhaseTileSpectrum:
        # Imported here: virtual_slide builds on this module's Slide.
        from focustrack_instrument_sim.virtual_slide import TissueSlide

        if isinstance(slide, TissueSlide):  # a window of one continuous section
            layers = slide.tile(row, col, self.spec.shape, self.pixel_size_um, view_um)
            spectra = self.renderer.spectra(layers.section, layers.dust)
            assert isinstance(spectra, TileSpectra)  # a stained section
            fold = None
            if layers.fold is not None:
                upper = self.renderer.spectra(layers.fold, None)
                assert isinstance(upper, TileSpectra)
                fold = upper.channels
            return replace(
                spectra, dust_dz_um=layers.dust_dz_um, fold=fold, fold_dz_um=layers.fold_dz_um
            )
        specimen_seed, dust_seed = self._tile_seeds(slide, row, col)
        specimen = self._specimen(specimen_seed, self.spec.shape, self.pixel_size_um)
        dust = None
        if self.spec.specimen.dust_density > 0:
            dust = dust_layer(self.spec.specimen, dust_seed, self.spec.shape, self.pixel_size_um)
        if view_um != (0.0, 0.0):  # a field of its own, seen elsewhere: it repeats (a phase
            # specimen's fields are drawn in place)
            shift_px = (-view_um[0] / self.pixel_size_um, -view_um[1] / self.pixel_size_um)
            if not isinstance(specimen, PhaseObject):
                specimen = wrapped_shift(specimen, shift_px)
            dust = None if dust is None else wrapped_shift(dust, shift_px)
        return self.renderer.spectra(specimen, dust)


def wrapped_shift(image: np.ndarray, shift_px: tuple[float, float]) -> np.ndarray:
    """A transmission (height, width[, channels]) moved by `shift_px` (rows, columns),
    periodic at its edges (the optics' FFTs treat it so already)."""
    from scipy import ndimage

    shift = (*shift_px, *([0.0] * (image.ndim - 2)))
    return ndimage.shift(image, shift, order=1, mode="grid-wrap").astype(image.dtype, copy=False)


def specimen_function(spec: MicroscopeSpec) -> SpecimenFn:
    """The specimen of `spec.specimen_kind`, with its composition from `spec`."""
    kinds: dict[str, SpecimenFn] = {
        "stained-smear": functools.partial(blood_smear, spec.specimen),
        "phase-cells": functools.partial(cell_culture, spec.phase_specimen),
        "phase-blood": functools.partial(red_cells, spec.phase_specimen),
    }
    return kinds[spec.specimen_kind]
