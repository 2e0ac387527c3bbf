"""A scan of overlapping tiles (a virtual slide's): the OME-Zarr mosaic is stitched at the
stage's positions, its images placed in the stage's micrometres, the map layers and the
kept planes images of their own; ome-zarr-models validates every one of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile
import zarr
from ome_zarr_models import open_ome_zarr
from ome_zarr_models.v05 import Image

from focustrack_core.domain import Acquisition, FocusMap, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler import outputs
from focustrack_scheduler.finished import FinishedScan, write_outputs
from focustrack_scheduler.outputs import MosaicFormat, WallTimes
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.writers import DEFAULT_WRITERS

TILE_PX, STEP_PX = 96, 80  # tiles of 96 px, 16 px of overlap
PIXEL_UM = 0.25
GRID = ScanGrid(2, 3, pitch_um=STEP_PX * PIXEL_UM, origin_x_um=1000.0, origin_y_um=500.0)
BIT_DEPTH = 8


def _specimen() -> np.ndarray:
    rng = np.random.default_rng(7)
    field = rng.integers(0, 256, (STEP_PX + TILE_PX, 2 * STEP_PX + TILE_PX, 3))
    return field.astype(np.uint16)


def _phase_specimen() -> np.ndarray:
    """A phase (rad) over the same field as `_specimen`, float32 (y, x)."""
    field = np.random.default_rng(8).uniform(-1.0, 1.0, (STEP_PX + TILE_PX, 2 * STEP_PX + TILE_PX))
    return field.astype(np.float32)


def _scan(out_dir: Path, mosaic_format: MosaicFormat = MosaicFormat.OME_ZARR) -> dict:
    specimen, phase = _specimen(), _phase_specimen()
    record = ScanRecord(out_dir)
    record.state.save(strategy="kf-2d", slide="slide-0", instrument="sim")
    record.state.save(
        tile={"height": TILE_PX, "width": TILE_PX, "channels": 3, "pixel_size_um": PIXEL_UM}
    )
    for index, tile in enumerate(GRID.serpentine):
        row, col = tile.row, tile.col
        acquisition = Acquisition(index, row, col, ZRange(-1.0, 0.5, 5), Purpose.SCAN, True)
        record.acquired(acquisition, 5, 1.0)
        measurement = Measurement(0.1 * col, 0.2)
        record.measurement(
            acquisition, measurement, Outcome(row, col, True, posterior_um=0.1), None
        )
        image = specimen[
            row * STEP_PX : row * STEP_PX + TILE_PX, col * STEP_PX : col * STEP_PX + TILE_PX
        ]
        record.keep(GRID, row, col, 0.0, image, BIT_DEPTH)
        if (row, col) != (1, 1):  # a tile whose phase did not come
            tile_rad = phase[
                row * STEP_PX : row * STEP_PX + TILE_PX, col * STEP_PX : col * STEP_PX + TILE_PX
            ]
            record.phase(
                GRID, row, col, sequence=100 + index, n_frames=11, scan_time_s=0.4,
                reference_z_um=0.0, field=np.stack([tile_rad, np.ones_like(tile_rad)]),
                background_share=0.0, error=None,
            )  # fmt: skip
    planes = np.stack([specimen[:TILE_PX, STEP_PX : STEP_PX + TILE_PX]] * 3)
    record.keep_planes(GRID, 0, 1, [-0.5, 0.0, 0.5], planes, BIT_DEPTH)
    rng = np.random.default_rng(4)
    focus_map = FocusMap(*[rng.normal(0.0, 1.0, GRID.shape) for _ in range(5)])
    scan = FinishedScan.of(record, GRID, focus_map, None, 1.0, WallTimes(), mosaic_format)
    write_outputs(scan, DEFAULT_WRITERS)
    record.close()
    return dict(scan.report)


def _transforms(image: Image) -> tuple[list[float], list[float]]:
    dataset = image.attributes.ome.multiscales[0].datasets[0]
    scale, translation = dataset.coordinateTransformations
    return list(scale.scale), list(translation.translation)


def test_the_mosaic_is_stitched_where_the_stage_put_the_tiles(tmp_path: Path) -> None:
    report = _scan(tmp_path)
    assert report["seam_error_px"] == pytest.approx(0.0, abs=0.2)
    path = tmp_path / outputs.MOSAIC_ZARR
    root = open_ome_zarr(path)
    assert isinstance(root, Image)
    scale, translation = _transforms(root)
    assert scale == [1.0, PIXEL_UM, PIXEL_UM]
    # the first pixel's centre: tile (0, 0)'s centre less half a tile, in stage um
    half_um = (TILE_PX / 2 - 0.5) * PIXEL_UM
    assert translation == pytest.approx([0.0, 500.0 - half_um, 1000.0 - half_um])
    mosaic = np.asarray(zarr.open_group(path, mode="r")["s0"])
    np.testing.assert_array_equal(mosaic.transpose(1, 2, 0), _specimen().astype(np.uint8))


def test_a_finished_scan_run_again_reports_its_seam_error_still(tmp_path: Path) -> None:
    """Its tiles are in the mosaic alone by then: the report said `seam_error_px: null`."""
    first = _scan(tmp_path)
    assert not (tmp_path / outputs.PARTIAL_MOSAIC).exists()
    record = ScanRecord(tmp_path)
    again = FinishedScan.of(record, GRID, FocusMap(*[np.zeros(GRID.shape)] * 5), None, 1.0,
                            WallTimes(), MosaicFormat.OME_ZARR)  # fmt: skip
    record.close()
    assert again.report["seam_error_px"] == first["seam_error_px"] is not None


def test_the_phase_lies_pixel_for_pixel_over_the_stitched_mosaic(tmp_path: Path) -> None:
    """The phase layer has the stitched mosaic's shape and placement: each tile's phase where
    its image is (it used to lie side by side, at the tiles' full size, from (0, 0))."""
    _scan(tmp_path)
    path = tmp_path / outputs.MOSAIC_ZARR
    mosaic = open_ome_zarr(path)
    phase = Image.from_zarr(zarr.open_group(path / outputs.ZARR_PHASE, mode="r"))
    assert isinstance(mosaic, Image)
    assert _transforms(phase) == _transforms(mosaic)
    phase_rad = np.asarray(zarr.open_group(path / outputs.ZARR_PHASE, mode="r")["s0"])[0]
    assert phase_rad.shape == _specimen().shape[:2]
    expected = np.where(np.isnan(phase_rad), np.nan, _phase_specimen())
    np.testing.assert_array_equal(phase_rad, expected)  # every phase pixel at its place
    assert np.isnan(phase_rad[TILE_PX:, STEP_PX + 16 : 2 * STEP_PX]).all()  # (1, 1) alone
    assert not np.isnan(phase_rad[:STEP_PX]).any()  # the first row's tiles all have one


def test_the_preview_and_the_ome_tiff_are_stitched_too(tmp_path: Path) -> None:
    from PIL import Image as PillowImage

    _scan(tmp_path, MosaicFormat.OME_TIFF)
    specimen = _specimen().astype(np.uint8)
    preview = np.asarray(PillowImage.open(tmp_path / outputs.MOSAIC_PREVIEW))
    np.testing.assert_array_equal(preview, specimen)  # not tiles side by side, overlaps twice
    np.testing.assert_array_equal(tifffile.imread(tmp_path / outputs.MOSAIC), specimen)


def test_the_map_layers_and_planes_are_images_at_the_stage_positions(tmp_path: Path) -> None:
    _scan(tmp_path)
    path = tmp_path / outputs.MOSAIC_ZARR
    group = zarr.open_group(path, mode="r")
    for name in group.attrs[outputs.ZARR_ATTRS]["maps"].values():
        layer = Image.from_zarr(zarr.open_group(path / name, mode="r"))
        scale, translation = _transforms(layer)
        assert scale == [GRID.pitch_um, GRID.pitch_um]
        assert translation == [500.0, 1000.0]  # tile (0, 0)'s value at its stage position
    planes = Image.from_zarr(zarr.open_group(path / outputs.ZARR_PLANES / "r0_c1", mode="r"))
    scale, translation = _transforms(planes)
    assert [axis.name for axis in planes.attributes.ome.multiscales[0].axes] == ["c", "z", "y", "x"]
    half_um = (TILE_PX / 2 - 0.5) * PIXEL_UM
    assert scale == [1.0, 0.5, PIXEL_UM, PIXEL_UM]
    assert translation == pytest.approx(
        [0.0, -0.5, 500.0 - half_um, 1000.0 + GRID.pitch_um - half_um]
    )
    attributes = zarr.open_group(path / outputs.ZARR_PLANES / "r0_c1", mode="r").attrs
    assert attributes[outputs.ZARR_ATTRS]["z_um"] == [-0.5, 0.0, 0.5]
    frames = np.asarray(zarr.open_group(path / outputs.ZARR_PLANES / "r0_c1", mode="r")["s0"])
    assert frames.shape == (3, 3, TILE_PX, TILE_PX)
