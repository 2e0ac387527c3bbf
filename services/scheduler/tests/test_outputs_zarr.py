"""The OME-Zarr mosaic: read with ome-zarr-py's reader, its metadata checked against the record."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import tifffile
import zarr
from ome_zarr.io import parse_url
from ome_zarr.reader import Multiscales, Reader

from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    ZRange,
)
from focustrack_core.fusion import fuse_planes
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler import outputs
from focustrack_scheduler.finished import FinishedScan, write_outputs
from focustrack_scheduler.in_focus import InFocusScore
from focustrack_scheduler.mosaic_store import to_uint8
from focustrack_scheduler.ome_zarr import write_mosaic
from focustrack_scheduler.outputs import MosaicFormat, WallTimes
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.scan import summary_line
from focustrack_scheduler.writers import DEFAULT_WRITERS

GRID = ScanGrid(2, 3, pitch_um=150.0)
TILE_PX = 256  # a 512 x 768 mosaic: one 2x halving on top of full resolution
BIT_DEPTH = 12
PIXEL_UM = 0.25


def scanned_record(out_dir: Path) -> tuple[ScanRecord, np.ndarray]:
    """A record of a scan of GRID: tile (0, 1) retried after an edge, tile (1, 2) flat."""
    rng = np.random.default_rng(3)
    record = ScanRecord(out_dir)
    record.state.save(strategy="kf-2d", slide="slide-0", instrument="sim")
    record.state.save(
        tile={"height": TILE_PX, "width": TILE_PX, "channels": 3, "pixel_size_um": PIXEL_UM}
    )
    images = rng.integers(0, 2**BIT_DEPTH, (*GRID.shape, TILE_PX, TILE_PX, 3), dtype=np.uint16)
    index = 0
    for tile in GRID.serpentine:
        row, col = tile.row, tile.col
        measurements = [Measurement(10.0 + row + 0.1 * col, 0.2 + 0.01 * col)]
        if (row, col) == (0, 1):
            measurements.insert(0, Measurement(8.0, 0.3, frozenset({FocusFlag.EDGE_LOW})))
        if (row, col) == (1, 2):
            measurements = [Measurement(None, None, frozenset({FocusFlag.FLAT}))]
        for attempt, measurement in enumerate(measurements):
            purpose = Purpose.SCAN if attempt == 0 else Purpose.RETRY
            acquisition = Acquisition(index, row, col, ZRange(5.0, 0.5, 9), purpose, True)
            record.acquired(acquisition, 9, 1.5)
            outcome = Outcome(row, col, measurement.z_um is not None, posterior_um=measurement.z_um)
            record.measurement(acquisition, measurement, outcome, None)
            index += 1
        record.keep(GRID, row, col, 10.0 + row, images[row, col], BIT_DEPTH)
    return record, images


def focus_map() -> FocusMap:
    rng = np.random.default_rng(4)
    layers = [rng.normal(10.0, 1.0, GRID.shape) for _ in range(5)]
    layers[2][1, 2] = np.nan  # no posterior where the curve was flat
    return FocusMap(*layers)


def finish(
    record: ScanRecord,
    truth_um: np.ndarray | None = None,
    mosaic_format: MosaicFormat = MosaicFormat.OME_ZARR,
) -> dict:
    """Write the default outputs of the scan `record` holds; its report."""
    scan = FinishedScan.of(record, GRID, focus_map(), truth_um, 1.0, WallTimes(), mosaic_format)
    write_outputs(scan, DEFAULT_WRITERS)
    return dict(scan.report)


def write(tmp_path: Path, mosaic_format: MosaicFormat) -> tuple[dict, ScanRecord, np.ndarray]:
    record, images = scanned_record(tmp_path)
    return finish(record, mosaic_format=mosaic_format), record, images


def test_the_ome_zarr_mosaic_opens_with_ome_zarr_py_and_holds_the_scan_record(
    tmp_path: Path,
) -> None:
    report, record, images = write(tmp_path, MosaicFormat.OME_ZARR)
    path = tmp_path / outputs.MOSAIC_ZARR
    assert report["mosaic"] == outputs.MOSAIC_ZARR
    assert not (tmp_path / outputs.PARTIAL_MOSAIC).exists()

    node = next(iter(Reader(parse_url(path))()))
    assert any(isinstance(spec, Multiscales) for spec in node.specs)
    levels = [np.asarray(level) for level in node.data]
    assert [level.shape for level in levels] == [(3, 512, 768), (3, 256, 384)]
    expected = to_uint8(images, BIT_DEPTH).transpose(4, 0, 2, 1, 3).reshape(3, 512, 768)
    np.testing.assert_array_equal(levels[0], expected)
    axes = node.metadata["axes"]
    assert [axis["name"] for axis in axes] == ["c", "y", "x"]
    assert axes[1]["unit"] == "micrometer"
    assert node.metadata["coordinateTransformations"][0][0]["scale"] == [1.0, PIXEL_UM, PIXEL_UM]

    attributes = zarr.open_group(path, mode="r").attrs[outputs.ZARR_ATTRS]
    assert attributes["grid"] == {"rows": 2, "cols": 3, "pitch_um": 150.0}
    assert attributes["scan"]["strategy"] == "kf-2d"
    tiles = {(tile["row"], tile["col"]): tile for tile in attributes["tiles"]}
    assert len(tiles) == GRID.n_tiles
    for (row, col), measured in record.tally.measured.items():
        tile = tiles[(row, col)]
        assert tile["best_z_um"] == measured["z_um"]
        assert tile["sigma_um"] == measured["sigma_um"]
        assert tile["flags"] == measured["flags"]
        assert tile["z_used_um"] == record.tally.kept[(row, col)]
        assert tile["stage_x_um"] == col * 150.0
    assert tiles[(0, 1)]["images"] == 18 and tiles[(0, 0)]["images"] == 9  # the retry counts
    assert tiles[(0, 1)]["flags"] == [] and tiles[(0, 1)]["best_z_um"] == pytest.approx(10.1)
    assert tiles[(1, 2)]["flags"] == ["flat"] and tiles[(1, 2)]["best_z_um"] is None
    assert tiles[(1, 2)]["posterior_um"] is None  # JSON has no NaN

    layers = {
        "posterior_um": focus_map().posterior_um,
        "posterior_sigma_um": focus_map().posterior_sigma_um,
    }
    for name, values in layers.items():
        assert attributes["maps"][name] == f"{outputs.ZARR_MAPS}/{name}"
        layer = next(iter(Reader(parse_url(path / outputs.ZARR_MAPS / name))()))
        np.testing.assert_array_equal(np.asarray(layer.data[0]), values)
        transform = layer.metadata["coordinateTransformations"][0]
        tile_um = TILE_PX * PIXEL_UM  # one value per tile, centred on its tile of the mosaic
        assert transform[0]["scale"] == [tile_um, tile_um]
        assert transform[1]["translation"] == [(tile_um - PIXEL_UM) / 2] * 2
    images_map = next(iter(Reader(parse_url(path / outputs.ZARR_MAPS / "images"))()))
    images_per_tile = record.tally.images_per_tile(GRID)
    np.testing.assert_array_equal(np.asarray(images_map.data[0]), images_per_tile)


def test_ome_tiff_stays_an_option(tmp_path: Path) -> None:
    report, _, _ = write(tmp_path, MosaicFormat.OME_TIFF)
    assert report["mosaic"] == outputs.MOSAIC
    assert not (tmp_path / outputs.MOSAIC_ZARR).exists()
    with tifffile.TiffFile(tmp_path / outputs.MOSAIC) as tif:
        assert tif.is_ome and tif.series[0].shape == (512, 768, 3)


def test_the_frames_a_tile_keeps_are_on_disk_read_back_and_judged_for_focus(
    tmp_path: Path,
) -> None:
    record, images = scanned_record(tmp_path)
    planes = np.stack([images[0, 0], images[0, 1], images[1, 0]])
    record.keep_planes(GRID, 0, 0, [9.0, 10.0, 11.0], planes, BIT_DEPTH)
    np.testing.assert_array_equal(np.load(tmp_path / outputs.PLANES / "r0_c0.npy"), planes)
    # the tile's image in the mosaic is now their fusion
    mosaic = np.load(tmp_path / outputs.PARTIAL_MOSAIC)
    fused = to_uint8(fuse_planes(planes), BIT_DEPTH)
    np.testing.assert_array_equal(mosaic[:TILE_PX, :TILE_PX], fused)
    # kept at 10 (its image) and at 9, 10, 11: in focus within 1.5 um with 1 um of depth of field
    truth_um = np.full(GRID.shape, 100.0)
    truth_um[0, 0] = 11.3
    tally = record.tally
    assert InFocusScore(truth_um, 1.0).tiles(tally.kept, tally.planes) == 1
    assert InFocusScore(truth_um, 0.5).tiles(tally.kept, tally.planes) == 0
    record.close()
    again = ScanRecord(tmp_path)  # a restarted scheduler reads them back from the log
    assert again.tally.planes == {(0, 0): [9.0, 10.0, 11.0]}
    report = finish(again, truth_um)
    assert report["in_focus_fraction"] == pytest.approx(1 / GRID.n_tiles)
    assert report["frames_kept_per_tile"] == pytest.approx((GRID.n_tiles + 2) / GRID.n_tiles)


def phase_of(tile: tuple[int, int]) -> np.ndarray:
    """A tile's field as the phase service sends it: float32 (2, h, w), phase then amplitude."""
    rng = np.random.default_rng(tile)
    phase_rad = rng.uniform(-math.pi, math.pi, (TILE_PX, TILE_PX))
    return np.stack([phase_rad, np.ones_like(phase_rad)]).astype(np.float32)


def test_the_phase_of_the_tiles_is_an_image_in_radians_over_the_mosaic(tmp_path: Path) -> None:
    record, _ = scanned_record(tmp_path)
    common = {"n_frames": 11, "scan_time_s": 0.4, "reference_z_um": 10.0}
    for index, tile in enumerate([(0, 0), (0, 2), (1, 1)]):
        record.phase(
            GRID, *tile, sequence=100 + index, **common, field=phase_of(tile),
            background_share=0.4, error=None,
        )  # fmt: skip
    record.phase(
        GRID, 1, 2, sequence=103, **common, field=None, background_share=None,
        error="no phase result",
    )  # fmt: skip
    record.close()
    again = ScanRecord(tmp_path)  # read back from the log, as a restarted scheduler does
    report = finish(again)
    assert report["tiles_with_phase"] == 3 and report["phase_images_acquired"] == 44
    assert report["tiles_phase_asked"] == 4  # (1, 2): asked, no result
    line = summary_line(report)  # a tile without phase used to go unsaid
    assert f"phase on 3 of {GRID.n_tiles} tiles; WARNING: no phase on 1 tiles" in line
    assert report["phase_scan_time_s"] == pytest.approx(1.6)
    assert report["images_acquired"] == 9 * (GRID.n_tiles + 1)  # the focus figures alone

    path = tmp_path / outputs.MOSAIC_ZARR
    node = next(iter(Reader(parse_url(path / outputs.ZARR_PHASE))()))
    levels = [np.asarray(level) for level in node.data]
    assert [level.shape for level in levels] == [(1, 512, 768), (1, 256, 384)]  # as the mosaic's
    phase = levels[0][0].reshape(2, TILE_PX, 3, TILE_PX).transpose(0, 2, 1, 3)
    for row, col in np.ndindex(GRID.shape):
        if (row, col) in again.tally.phase:
            np.testing.assert_array_equal(phase[row, col], phase_of((row, col))[0])
        else:
            assert np.isnan(phase[row, col]).all()
    assert node.metadata["coordinateTransformations"][0][0]["scale"] == [1.0, PIXEL_UM, PIXEL_UM]
    group = zarr.open_group(path / outputs.ZARR_PHASE, mode="r")
    assert group.attrs[outputs.ZARR_ATTRS] == {"layer": "phase", "unit": "radian"}
    assert group.attrs["ome"]["omero"]["channels"][0]["label"] == "phase (rad)"


def test_without_phase_the_ome_zarr_has_no_phase_image(tmp_path: Path) -> None:
    report, _, _ = write(tmp_path, MosaicFormat.OME_ZARR)
    assert report["tiles_with_phase"] == 0
    assert outputs.ZARR_PHASE not in zarr.open_group(tmp_path / outputs.MOSAIC_ZARR, mode="r")


def test_a_monochrome_cameras_mosaic_is_one_grey_channel(tmp_path: Path) -> None:
    """Micro-Manager's monochrome cameras give one channel: grey, not "red"."""
    path = tmp_path / "mono.ome.zarr"
    write_mosaic(path, np.zeros((600, 520, 1), np.uint8), 0.5)
    omero = zarr.open_group(path, mode="r").attrs["ome"]["omero"]
    assert [(c["label"], c["color"]) for c in omero["channels"]] == [("grey", "FFFFFF")]
    assert omero["rdefs"]["model"] == "greyscale"
    rgb = tmp_path / "rgb.ome.zarr"
    write_mosaic(rgb, np.zeros((600, 520, 3), np.uint8), 0.5)
    omero = zarr.open_group(rgb, mode="r").attrs["ome"]["omero"]
    assert [c["label"] for c in omero["channels"]] == ["red", "green", "blue"]
    assert omero["rdefs"]["model"] == "color"


def test_a_finished_scan_run_again_names_the_mosaic_it_wrote(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Run again on a finished folder (its partial mosaic gone), in another format: the
    report names the mosaic written before, and a warning says the other cannot be written
    (the report used to say `"mosaic": null`, silently)."""
    report, record, _ = write(tmp_path, MosaicFormat.OME_ZARR)
    assert report["mosaic"] == outputs.MOSAIC_ZARR
    assert not (tmp_path / outputs.PARTIAL_MOSAIC).exists()
    again = finish(record, mosaic_format=MosaicFormat.OME_TIFF)
    assert again["mosaic"] == outputs.MOSAIC_ZARR
    assert not (tmp_path / outputs.MOSAIC).exists()
    assert "cannot be written again as mosaic.ome.tif" in caplog.text
    assert finish(record)["mosaic"] == outputs.MOSAIC_ZARR  # the same format: named, quiet
    record.close()
