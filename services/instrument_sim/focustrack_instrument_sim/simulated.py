"""The simulator as an `Instrument` (`--backend sim`): `SimulatedInstrument` over
`microscope.Microscope`, and the microscope its options describe (`SimulatorOptions`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from focustrack_core.drift import ThermalDrift
from focustrack_core.laser import LaserSpec
from focustrack_core.surfaces import family_spec
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    Description,
    FocusTruth,
    Frames,
    OpticsInfo,
    Refusal,
    SlideLayout,
    StackPlan,
    StackRequest,
    TileContents,
    TilePhase,
)
from focustrack_instrument_sim.laser import SimulatedLaser
from focustrack_instrument_sim.microscope import (
    Microscope,
    MicroscopeSpec,
    SimulatedPlan,
    slides_from_map,
    slides_from_seed,
)
from focustrack_instrument_sim.optics import Illumination, Optics
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_instrument_sim.specimen import SpecimenSpec
from focustrack_instrument_sim.stage import StageSpec
from focustrack_instrument_sim.virtual_slide import TissueSlide, TissueSlideSpec, tissue_slides


class SimulatedInstrument:
    """A `Microscope` as an `Instrument`, a `TruthSource` and a `PhaseTruthSource`: its
    frames, simulated timing and refusals, unchanged. Its stage moves (and its clock
    advances) in `plan`."""

    def __init__(self, scope: Microscope, laser: SimulatedLaser | None = None) -> None:
        self.microscope = scope
        self.laser = laser  # the reflection autofocus, where it has one

    def describe(self) -> Description:
        spec = self.microscope.spec
        optics = spec.optics
        return Description(
            slides=tuple(
                SlideLayout(slide.name, slide.grid) for slide in self.microscope.slides.values()
            ),
            frame=spec.frame,
            optics=OpticsInfo(
                pixel_size_um=optics.pixel_size_um,
                numerical_aperture=optics.numerical_aperture,
                magnification=optics.magnification,
                wavelength_um=optics.reference_wavelength_um,
                refractive_index=optics.refractive_index,
                depth_of_field_um=optics.depth_of_field_um,
            ),
            z_range_um=spec.stage.z_range_um,
            max_frames=spec.max_frames,
            default_exposure_s=spec.stage.timing.exposure_s,
        )

    def plan(self, request: StackRequest) -> StackPlan:
        return self.microscope.plan(
            request.slide,
            request.row,
            request.col,
            request.z_low_um,
            request.z_step_um,
            request.n_frames,
            request.exposure_s,
            request.purpose,
            request.reference_z_um,
            stage_offset_um=(request.stage_offset_x_um, request.stage_offset_y_um),
        )

    def acquire(self, plan: StackPlan, out: Callable[[int], np.ndarray]) -> Frames:
        if not isinstance(plan, SimulatedPlan):
            raise TypeError(f"not a plan of the simulator: {type(plan).__name__}")
        return self.microscope.render(plan, out)

    def truth(self, slide: str) -> FocusTruth:
        if slide not in self.microscope.slides:
            raise AcquisitionRefusedError(
                Refusal.UNKNOWN_SLIDE, f"unknown slide {slide!r}", "slide"
            )
        focus_um, drift_um = self.microscope.truth_um(slide)
        chosen = self.microscope.slides[slide]
        tiles = None
        if isinstance(chosen, TissueSlide):
            contents = chosen.truth()
            tiles = TileContents(
                contents.tissue_share,
                contents.empty,
                focus_um + contents.dust_dz_um,
                focus_um + contents.fold_dz_um,
            )
        offset_um = self.microscope.spec.stage.slide_offset_um
        return FocusTruth(focus_um, drift_um, self.microscope.stage.clock_s, tiles, offset_um)

    def phase_truth(self, slide: str, row: int, col: int) -> TilePhase:
        return self.microscope.true_phase(slide, row, col)

    def close(self) -> None:
        self.microscope.close()


def microscope_from_options(options: SimulatorOptions) -> Microscope:
    """The microscope the simulator's options describe."""
    if options.map is not None:
        slides = slides_from_map(options.map, options.seed, options.pitch_um)
    elif options.tissue_slide:
        surface = family_spec(options.family, options.rows, options.cols)
        pixel_um = Optics(magnification=options.magnification).pixel_size_um
        shape = (options.height, options.width)
        tissue = TissueSlideSpec(overlap=options.overlap)
        slides = list(tissue_slides(options.seed, options.slides, surface, shape, pixel_um, tissue))
    else:
        surface = family_spec(options.family, options.rows, options.cols)
        slides = slides_from_seed(options.seed, options.slides, surface, options.pitch_um)
    if options.z_offset_um:
        slides = [replace(slide, focus_um=slide.focus_um + options.z_offset_um) for slide in slides]
    spec = MicroscopeSpec(
        optics=Optics(numerical_aperture=options.na, magnification=options.magnification),
        stage=StageSpec(
            drift_um_per_s=options.drift_um_per_s,
            thermal=thermal_drift(options),
            slide_offset_um=(options.lateral_offset_x_um, options.lateral_offset_y_um),
        ),
        specimen=SpecimenSpec(dust_density=options.dust_density),
        specimen_kind=options.specimen,
        illumination=Illumination(condenser_na=options.condenser_na),
        height=options.height,
        width=options.width,
        max_frames=options.max_frames,
        cache_mb=options.cache_mb,
        workers=options.workers,
    )
    return Microscope(slides, spec, seed=options.seed)


def thermal_drift(options: SimulatorOptions) -> ThermalDrift | None:
    """The settling and random walk of the options' z drift (per seed), None if neither."""
    if not (options.drift_settle_um or options.drift_walk_um_per_sqrt_min):
        return None
    return ThermalDrift(
        settle_um=options.drift_settle_um,
        settle_tau_s=options.drift_settle_tau_s,
        walk_um_per_sqrt_min=options.drift_walk_um_per_sqrt_min,
        seed=options.seed,
    )


def simulated_instrument(options: SimulatorOptions) -> SimulatedInstrument:
    """The microscope of the options, with its laser autofocus where `--laser` asks."""
    scope = microscope_from_options(options)
    if not options.laser:
        return SimulatedInstrument(scope)
    spec = LaserSpec(
        noise_um=options.laser_noise_um,
        offset_um=options.laser_offset_um,
        offset_sigma_um=options.laser_offset_sigma_um,
    )
    return SimulatedInstrument(scope, SimulatedLaser(scope, spec, options.seed))
