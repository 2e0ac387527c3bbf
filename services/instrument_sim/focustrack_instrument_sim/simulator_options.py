"""The simulator's options (`--backend sim`): its slides and its microscope.

Declarations only (pydantic, and the core's map families and grid: numpy), so that the
service's settings compose them without loading the simulator: `--help` and a bad
option cost no scipy or OpenCV. The simulator's defaults are written here once: the
microscope's dataclasses (`MicroscopeSpec`, `Optics`, `StageSpec`, `SpecimenSpec`) take
theirs from these options (`default`), and the options take the slides' tile grid from
the core's (`SurfaceSpec`, `ScanGrid`). Bounds are here where nothing else checks a
value; the rest (even frame sides, the NA, the grid) the simulator's dataclasses refuse
when it opens, which ends the command with exit status 2 and their message.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, Field, FilePath, model_validator

from focustrack_core.geometry import MAX_GRID_SIDE, ScanGrid
from focustrack_core.settings import one_of
from focustrack_core.surfaces import FAMILIES, SurfaceSpec

#: The longest frame side the simulator renders, px: a scientific camera's sensor is at
#: most about 10000 px wide; 100000 px was taken, and each frame was then 10^10 pixels.
MAX_FRAME_SIDE_PX = 16384

#: A map family's name (--family): one of `FAMILIES`.
FamilyName = Annotated[str, one_of(FAMILIES)]

#: The specimens a slide may carry (--specimen): a Giemsa-stained blood smear (absorbing,
#: imaged incoherently), or unstained phase objects imaged with partially coherent light:
#: cells in culture, or a blood smear's red cells.
SPECIMENS = ("stained-smear", "phase-cells", "phase-blood")

#: A specimen's name (--specimen): one of `SPECIMENS`.
SpecimenName = Annotated[str, one_of(SPECIMENS)]


class SimulatorOptions(BaseModel):
    """The simulated microscope: generated slides (or a map file's) and its optics."""

    help_heading: ClassVar[str | None] = "the simulated microscope (--backend sim)"

    # the slides
    seed: int = Field(0, ge=0, description="seed of surfaces and specimens")
    slides: int = Field(1, ge=1, description="generated slides (slide-0, ...)")
    rows: int = Field(
        SurfaceSpec.rows, ge=1, le=MAX_GRID_SIDE, description="tiles per column of a slide"
    )
    cols: int = Field(
        SurfaceSpec.cols, ge=1, le=MAX_GRID_SIDE, description="tiles per row of a slide"
    )
    family: FamilyName = Field("standard", description="the map family of generated slides")
    map: FilePath | None = Field(
        None, description="true focus map(s) in um (.npy, .csv, .tif) to use instead"
    )
    pitch_um: float = Field(ScanGrid.pitch_um, description="tile centre spacing, um")
    specimen: SpecimenName = Field(
        "stained-smear",
        description="what every slide carries: " + ", ".join(SPECIMENS) + " (phase specimens "
        "are imaged with partially coherent light, see --condenser-na)",
    )
    z_offset_um: float = Field(
        0.0,
        description="every slide's focus moved by this much, um (a re-scan after drift "
        "between passes)",
    )
    lateral_offset_x_um: float = Field(
        0.0,
        description="every slide moved along x on the stage by this much, um (a re-scan after "
        "lateral drift between passes: the stage at x shows the slide's x minus this)",
    )
    lateral_offset_y_um: float = Field(
        0.0, description="the same along y, um (see --lateral-offset-x-um)"
    )
    tissue_slide: bool = Field(
        False,
        description="continuous virtual slides instead: one tissue section per slide with "
        "empty glass, holes, folds, tilt and coverslip dust, cut into tiles that overlap by "
        "--overlap (the pitch follows from the frame size; --pitch-um is not used)",
    )
    overlap: float = Field(
        0.1,
        ge=0,
        lt=0.5,
        description="share of a tile's side its neighbours share (--tissue-slide)",
    )
    # the microscope
    width: int = Field(1024, le=MAX_FRAME_SIDE_PX, description="frame width in pixels (even)")
    height: int = Field(1024, le=MAX_FRAME_SIDE_PX, description="frame height in pixels (even)")
    max_frames: int = Field(64, ge=1, description="largest z-stack accepted")
    workers: int = Field(2, ge=1, description="threads rendering the frames of a stack")
    cache_mb: float = Field(
        1024.0,
        ge=0,
        description="in-focus tile spectra kept, MB (16.8 MB a tile of 1024 x 1024, "
        "4.2 of 512 x 512)",
    )
    na: float = Field(0.85, description="numerical aperture")
    condenser_na: float = Field(
        0.2,
        ge=0,
        description="the condenser's numerical aperture for phase specimens (0: coherent "
        "light; at most --na)",
    )
    magnification: float = Field(60.0, description="magnification of the objective")
    drift_um_per_s: float = Field(0.0, description="thermal z drift, um/s")
    drift_settle_um: float = Field(
        0.0, description="warm-up settling of the z drift after start, um (exponential)"
    )
    drift_settle_tau_s: float = Field(
        200.0, gt=0, description="time constant of the warm-up settling, s"
    )
    drift_walk_um_per_sqrt_min: float = Field(
        0.0, ge=0, description="random walk of the z drift: its std after one minute, um"
    )
    dust_density: float = Field(0.0, ge=0, description="dust specks per 1000 um^2 (0: none)")
    laser: bool = Field(
        False,
        description="a reflection (laser) autofocus: the coverslip's height under a tile, "
        "queried on focustrack/v1/instrument/{name}/laser",
    )
    laser_noise_um: float = Field(0.05, ge=0, description="the laser reading's noise (std), um")
    laser_offset_um: float = Field(
        4.0, description="the tissue's focus above the coverslip interface, mean, um"
    )
    laser_offset_sigma_um: float = Field(
        0.4, ge=0, description="the spatial std of that offset (smooth over 10 tiles), um"
    )

    @model_validator(mode="after")
    def _grid_within_bounds(self) -> SimulatorOptions:
        # The grid's own bounds (the estimator's), checked here, before a slide's surface
        # is drawn: a grid of 10^10 tiles used to end in a MemoryError from the generator.
        ScanGrid(self.rows, self.cols)
        return self


def default(option: str) -> Any:
    """The default of the simulator's `option`, for the dataclass field that has it too."""
    return SimulatorOptions.model_fields[option].default
