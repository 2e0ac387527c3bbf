"""The MMCore backend's options (`--backend mmcore`): a Micro-Manager configuration, and
what a real microscope does not know (its slides, its optics, its limits).

Declarations only (pydantic), so that the service's settings compose them without loading
pymmcore-plus: `--help` and a bad option cost no Micro-Manager. The names start with
``mm_`` (flags ``--mm-...``) because every backend's options are flat flags of one command.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, ClassVar

from pydantic import BaseModel, Field
from pydantic_settings import NoDecode


class MMCoreOptions(BaseModel):
    """A microscope through Micro-Manager's device layer (pymmcore-plus `CMMCorePlus`)."""

    help_heading: ClassVar[str | None] = "a microscope through Micro-Manager (--backend mmcore)"

    # the devices
    mm_config: Path | None = Field(
        None,
        description="the Micro-Manager configuration (MMConfig.cfg) to load: it names the "
        "camera, the focus device, the XY stage and a pixel size configuration "
        "(needed with --backend mmcore)",
    )
    # NoDecode: from the environment, a list of folders separated by commas or spaces
    # (the service's `list_fields`), not JSON
    mm_adapter_path: Annotated[list[Path], NoDecode] = Field(
        [],
        description="folders holding the device adapters (libmmgr_dal_*); none: the "
        "Micro-Manager installation pymmcore-plus finds",
        json_schema_extra={"metavar": "DIR"},
    )
    mm_timeout_s: float = Field(
        5.0, gt=0, description="longest wait for a device (a move, a snap), s; then an error"
    )
    mm_xy_tolerance_um: float = Field(
        1.0, gt=0, description="an XY move ending farther than this from its target is an error, um"
    )
    mm_z_tolerance_um: float = Field(
        0.1,
        gt=0,
        description="a focus move ending farther than this from its target is an error, um",
    )
    mm_sequence: bool = Field(
        True,
        description="run stacks as hardware sequences where the focus device can "
        "(--no-mm-sequence: a move and a snap per frame)",
    )
    # the limits
    mm_z_min_um: float | None = Field(
        None, description="lowest focus position a stack may reach, um (default: the focus "
        "device's Position limits; required when it has none)"
    )  # fmt: skip
    mm_z_max_um: float | None = Field(
        None, description="highest focus position a stack may reach, um (default: the focus "
        "device's Position limits; required when it has none)"
    )  # fmt: skip
    mm_max_frames: int = Field(64, ge=1, description="largest z-stack accepted")
    # the slides: a real microscope knows none, so they are declared here
    mm_slides: int = Field(1, ge=1, description="slides on the stage (slide-0, ...)")
    mm_slide_spacing_um: float = Field(
        26_000.0, description="stage x from one slide's first tile to the next slide's, um"
    )
    mm_rows: int = Field(1, ge=1, description="tiles per column of a slide")
    mm_cols: int = Field(1, ge=1, description="tiles per row of a slide")
    mm_pitch_um: float | None = Field(
        None,
        gt=0,
        description="tile centre spacing, um (default: the field of view, the pixel size "
        "times the frame's shorter side, less --mm-overlap)",
    )
    mm_overlap: float = Field(
        0.0, ge=0, lt=1, description="fraction of the field of view neighbouring tiles share"
    )
    mm_origin_x_um: float | None = Field(
        None, description="stage x of slide-0's tile (0, 0), um (default: where the stage is)"
    )
    mm_origin_y_um: float | None = Field(
        None, description="stage y of slide-0's tile (0, 0), um (default: where the stage is)"
    )
    # the optics, which Micro-Manager does not know (its pixel size comes from the config)
    mm_pixel_size_um: float | None = Field(
        None,
        gt=0,
        description="a camera pixel in the specimen, um, where no pixel size configuration "
        "of the Micro-Manager configuration matches (one that matches wins)",
    )
    mm_na: float = Field(0.75, gt=0, description="numerical aperture of the objective")
    mm_magnification: float = Field(20.0, gt=0, description="magnification of the objective")
    mm_wavelength_um: float = Field(0.55, gt=0, description="wavelength of the light, um")
    mm_refractive_index: float = Field(
        1.0, ge=1, description="refractive index of the immersion medium (1: air)"
    )
