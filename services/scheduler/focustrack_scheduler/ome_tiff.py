"""The mosaic as a tiled, pyramidal OME-TIFF (``mosaic.ome.tif``) for QuPath and slide viewers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from focustrack_scheduler.pyramid import TIFF_TILE_PX, half, n_levels


def write_ome_tiff(path: Path, mosaic: np.ndarray, pixel_size_um: float, description: str) -> None:
    """The mosaic (height, width, channels) uint8 as a tiled OME-TIFF with its halvings
    (`pyramid.n_levels`) as sub-IFDs; pixels `pixel_size_um` wide."""
    levels = n_levels(mosaic.shape)
    options: dict[str, Any] = {
        "photometric": "rgb" if mosaic.shape[-1] == 3 else "minisblack",
        "tile": (TIFF_TILE_PX, TIFF_TILE_PX),
        "resolutionunit": "CENTIMETER",
    }
    metadata = {
        "axes": "YXS",
        "PhysicalSizeX": pixel_size_um,
        "PhysicalSizeXUnit": "µm",
        "PhysicalSizeY": pixel_size_um,
        "PhysicalSizeYUnit": "µm",
        "Description": description,
    }
    per_cm = 1e4 / pixel_size_um
    with tifffile.TiffWriter(path, bigtiff=mosaic.nbytes > 2**31) as tif:
        tif.write(
            mosaic,
            subifds=levels,
            resolution=(per_cm, per_cm),
            metadata=metadata,
            **options,
        )
        level = np.asarray(mosaic)
        for index in range(1, levels + 1):
            level = half(level)
            scale = per_cm / 2**index
            tif.write(level, subfiletype=1, resolution=(scale, scale), **options)
