"""The mosaic as OME-Zarr (``mosaic.ome.zarr``, NGFF 0.5): the image, then the scan's metadata.

`write_mosaic` writes the multiscale image (c, y, x); `write_metadata` adds, in the same
group, FocusTrack's attributes (`ZARR_ATTRS`: the scan, the grid, every tile's numbers) and
the focus-map layers in `ZARR_MAPS`, one NGFF image each, a pixel per tile, placed over its
tile of the mosaic (micrometres), so a viewer overlays them; `write_phase` the phase
(radians, with ``--phase``) in `ZARR_PHASE`, an NGFF image of the mosaic's pixels and
placement.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from focustrack_scheduler.outputs import ZARR_ATTRS, ZARR_MAPS, ZARR_PHASE, ZARR_PLANES
from focustrack_scheduler.pyramid import TIFF_TILE_PX, half, n_levels

#: Colours of the mosaic's channels in OME-Zarr's "omero" rendering settings.
_CHANNEL_COLOURS = (("red", "FF0000"), ("green", "00FF00"), ("blue", "0000FF"))
#: The one channel of a monochrome camera's mosaic.
_GREY = ("grey", "FFFFFF")
_SPACE = {"type": "space", "unit": "micrometer"}
#: NGFF version written (https://ngff.openmicroscopy.org/0.5/).
NGFF_VERSION = "0.5"


def write_mosaic(
    path: Path,
    mosaic: np.ndarray,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
) -> None:
    """The mosaic (height, width, channels) uint8 as a new NGFF image (c, y, x) at `path`,
    with its 2x2-mean halvings (`pyramid.n_levels`, as the OME-TIFF's pyramid); its first
    pixel's centre at `origin_um` (y, x): the stage's coordinates, for a stitched mosaic."""
    root = zarr.open_group(path, mode="w", zarr_format=3)
    levels = [mosaic]
    for _ in range(n_levels(mosaic.shape)):
        levels.append(half(np.asarray(levels[-1])))
    grey = mosaic.shape[-1] == 1  # a monochrome camera's
    channels = [
        {"label": label, "color": colour, "window": {"start": 0, "end": 255, "min": 0, "max": 255}}
        for label, colour in ((_GREY,) if grey else _CHANNEL_COLOURS[: mosaic.shape[-1]])
    ]
    _write_ngff_image(
        root,
        "mosaic",
        [level.transpose(2, 0, 1) for level in levels],
        pixel_um=(pixel_size_um, pixel_size_um),
        origin_um=origin_um,
        omero={"channels": channels, "rdefs": {"model": "greyscale" if grey else "color"}},
    )


def write_phase(
    path: Path,
    phase_rad: np.ndarray,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Into the OME-Zarr mosaic at `path`: `phase_rad` (height, width) float32, the phase in
    radians over the whole mosaic (NaN where a tile has none), as an NGFF image (c, y, x) of
    one channel in `ZARR_PHASE`, with the mosaic's pixels and halvings, its first pixel's
    centre at `origin_um` (y, x: the mosaic's, `write_mosaic`); its rendering window is
    [-pi, pi] and its unit ``radian`` (`ZARR_ATTRS`)."""
    root = zarr.open_group(path, mode="r+", zarr_format=3)
    levels = [phase_rad[..., None]]
    for _ in range(n_levels(phase_rad.shape)):
        levels.append(half(levels[-1]))
    window = {"start": -math.pi, "end": math.pi, "min": -math.pi, "max": math.pi}
    group = root.create_group(ZARR_PHASE)
    _write_ngff_image(
        group,
        ZARR_PHASE,
        [level.transpose(2, 0, 1) for level in levels],
        pixel_um=(pixel_size_um, pixel_size_um),
        origin_um=origin_um,
        omero={
            "channels": [{"label": "phase (rad)", "color": "FFFFFF", "window": window}],
            "rdefs": {"model": "greyscale"},
        },
    )
    group.attrs[ZARR_ATTRS] = {"layer": ZARR_PHASE, "unit": "radian"}


def write_metadata(
    path: Path,
    mosaic_shape: tuple[int, ...],
    pixel_size_um: float,
    attributes: dict[str, Any],
    layers: dict[str, np.ndarray],
    stage: tuple[float, tuple[float, float]] | None = None,
) -> None:
    """Into the OME-Zarr mosaic at `path` (of `mosaic_shape`, pixels `pixel_size_um` wide):
    `attributes` under `ZARR_ATTRS`, and each (rows, cols) layer as an NGFF image in
    `ZARR_MAPS`, one pixel per tile, placed over its tile of the mosaic (micrometres): at
    the stage's positions where `stage` gives the grid's pitch and tile (0, 0)'s centre
    (y, x), um (a stitched mosaic), else over the tiles side by side."""
    root = zarr.open_group(path, mode="r+", zarr_format=3)
    root.attrs[ZARR_ATTRS] = attributes
    rows, cols = next(iter(layers.values())).shape
    if stage is not None:
        pitch_um, centre_um = stage
        tile_um = (pitch_um, pitch_um)
    else:
        tile_um = (mosaic_shape[0] / rows * pixel_size_um, mosaic_shape[1] / cols * pixel_size_um)
        # a tile's value sits at the centre of its tile of the mosaic (NGFF places pixel centres)
        centre_um = ((tile_um[0] - pixel_size_um) / 2, (tile_um[1] - pixel_size_um) / 2)
    maps = root.create_group(ZARR_MAPS)
    for name, values in layers.items():
        group = maps.create_group(name)
        _write_ngff_image(group, name, [np.asarray(values)], tile_um, centre_um)
        unit = {"images": "images", "out_of_focus_risk": "probability"}.get(name, "um")
        group.attrs[ZARR_ATTRS] = {"layer": name, "unit": unit}


def write_planes(
    path: Path,
    tile: tuple[int, int],
    frames: np.ndarray,
    z_um: list[float],
    pixel_size_um: float,
    origin_um: tuple[float, float],
) -> None:
    """Into the OME-Zarr mosaic at `path`: the frames a tile keeps besides its image, (n, h,
    w, channels) ascending in z, as an NGFF image (c, z, y, x) in ``ZARR_PLANES/r{row}_c{col}``
    placed where the tile lies in the mosaic (its first pixel's centre at `origin_um`); its
    planes' z (um) in its attributes (`ZARR_ATTRS`), and their mean step as the z scale."""
    root = zarr.open_group(path, mode="r+", zarr_format=3)
    planes = root.require_group(ZARR_PLANES)
    name = f"r{tile[0]}_c{tile[1]}"
    group = planes.create_group(name)
    step_um = float(np.mean(np.diff(z_um))) if len(z_um) > 1 else 1.0
    _write_ngff_image(
        group,
        name,
        [frames.transpose(3, 0, 1, 2)],
        pixel_um=(pixel_size_um, pixel_size_um),
        origin_um=origin_um,
        z=(step_um, float(z_um[0])),
    )
    group.attrs[ZARR_ATTRS] = {"layer": ZARR_PLANES, "row": tile[0], "col": tile[1], "z_um": z_um}


def _write_ngff_image(
    group: zarr.Group,
    name: str,
    levels: list[np.ndarray],
    pixel_um: tuple[float, float],
    origin_um: tuple[float, float],
    z: tuple[float, float] | None = None,
    **metadata: Any,
) -> None:
    """An NGFF multiscale image in `group`: `levels` (c, y, x) or (y, x), each half the last,
    or with `z` (its step and first plane, um) one level (c, z, y, x).

    `pixel_um` is level 0's pixel size (y, x) and `origin_um` the centre of its first pixel.
    """
    names = ["c", "y", "x"][-levels[0].ndim :] if z is None else ["c", "z", "y", "x"]
    axes = [{"name": "c", "type": "channel"}] if "c" in names else []
    axes += [{"name": axis, **_SPACE} for axis in names if axis != "c"]
    datasets: list[dict[str, Any]] = []
    for index, level in enumerate(levels):
        factor = 2**index
        chunks = (*level.shape[:-2], *(min(side, 2 * TIFF_TILE_PX) for side in level.shape[-2:]))
        array = group.create_array(
            f"s{index}", shape=level.shape, dtype=level.dtype, chunks=chunks, dimension_names=names
        )
        array[...] = level
        scale = [size * factor for size in pixel_um]
        # the centre of a level's first pixel: the mean of the factor x factor it averages
        translation = [
            o + (factor - 1) * size / 2 for o, size in zip(origin_um, pixel_um, strict=True)
        ]
        channel = [1.0] if "c" in names else []
        channel_offset = [0.0] if "c" in names else []
        if z is not None:  # one level: the planes as the camera took them
            scale, translation = [z[0], *scale], [z[1], *translation]
        datasets.append(
            {
                "path": f"s{index}",
                "coordinateTransformations": [
                    {"type": "scale", "scale": channel + scale},
                    {"type": "translation", "translation": channel_offset + translation},
                ],
            }
        )
    multiscale: dict[str, Any] = {"name": name, "axes": axes, "datasets": datasets}
    group.attrs["ome"] = {"version": NGFF_VERSION, "multiscales": [multiscale], **metadata}
