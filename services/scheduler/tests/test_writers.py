"""Each output writer on a made-up finished scan: its files appear with what they should hold."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pytest
import tifffile
import zarr
from matplotlib.image import imread

from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import focus_map_of_npy, map_csv
from focustrack_scheduler import outputs
from focustrack_scheduler.finished import FinishedScan, write_outputs
from focustrack_scheduler.outputs import MosaicFormat
from focustrack_scheduler.writers import (
    DEFAULT_WRITERS,
    FocusMapWriter,
    MosaicPreviewWriter,
    MosaicWriter,
    OmeZarrMetadataWriter,
    PlotsWriter,
    ReportWriter,
)

GRID = ScanGrid(2, 3, pitch_um=150.0)
TILE_PX = 8
PIXEL_UM = 0.5


def finished_scan(
    out_dir: Path, mosaic_format: MosaicFormat = MosaicFormat.OME_ZARR
) -> FinishedScan:
    """A scan of GRID as a record would leave it: a partial mosaic on disk, two tiles measured."""
    rng = np.random.default_rng(7)
    mosaic = rng.integers(0, 256, (2 * TILE_PX, 3 * TILE_PX, 3), dtype=np.uint8)
    np.save(out_dir / outputs.PARTIAL_MOSAIC, mosaic)
    layers = [rng.normal(10.0, 1.0, GRID.shape) for _ in range(5)]
    state = {
        "strategy": "kf-2d",
        "instrument": "sim",
        "slide": "slide-0",
        "slide_id": "abc",
        "tile": {"height": TILE_PX, "width": TILE_PX, "channels": 3, "pixel_size_um": PIXEL_UM},
    }
    return FinishedScan(
        out_dir=out_dir,
        grid=GRID,
        dof_um=1.0,
        focus_map=FocusMap(*layers),
        truth_um=np.full(GRID.shape, 10.0),
        state=MappingProxyType(state),
        kept=MappingProxyType({(0, 0): 10.5, (1, 2): 9.0}),
        planes=MappingProxyType({(1, 2): (8.5, 9.0)}),
        measured=MappingProxyType(
            {(0, 0): {"z_um": 10.4, "sigma_um": 0.1, "flags": ["ambiguous"]}}
        ),
        images_per_tile=np.array([[5, 0, 0], [0, 0, 9]]),
        mosaic=np.load(out_dir / outputs.PARTIAL_MOSAIC, mmap_mode="r"),
        mosaic_format=mosaic_format,
        report=MappingProxyType({"strategy": "kf-2d", "mosaic": mosaic_format.file_name}),
    )


def test_the_focus_map_writer_writes_the_estimators_export(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    csv, npy = FocusMapWriter().write(scan)
    assert csv.read_text() == map_csv(scan.focus_map, GRID)
    np.testing.assert_array_equal(
        focus_map_of_npy(npy.read_bytes()).posterior_um, scan.focus_map.posterior_um
    )


def test_the_plots_and_the_preview_are_pngs_the_preview_pixel_for_pixel(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    (plots,) = PlotsWriter().write(scan)
    assert imread(plots).shape[:2] == (810, 990)  # 11 x 9 inches at 90 dpi
    (preview,) = MosaicPreviewWriter().write(scan)
    assert preview == tmp_path / outputs.MOSAIC_PREVIEW
    pixels = np.rint(imread(preview)[..., :3] * 255).astype(np.uint8)
    assert scan.mosaic is not None
    np.testing.assert_array_equal(pixels, scan.mosaic)


def test_a_one_channel_mosaic_previews_as_a_grey_png_pixel_for_pixel(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    assert scan.mosaic is not None
    grey = np.ascontiguousarray(scan.mosaic[..., :1])  # a monochrome camera's mosaic
    (preview,) = MosaicPreviewWriter().write(replace(scan, mosaic=grey))
    pixels = imread(preview)
    assert pixels.ndim == 2  # one channel in the file, not three copies
    np.testing.assert_array_equal(np.rint(pixels * 255).astype(np.uint8), grey[..., 0])


def test_the_mosaic_writer_writes_the_mosaic_in_the_scans_format(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    assert MosaicWriter().write(scan) == [tmp_path / outputs.MOSAIC_ZARR]
    root = zarr.open_group(tmp_path / outputs.MOSAIC_ZARR, mode="r")
    assert scan.mosaic is not None  # still readable: mapped in memory
    np.testing.assert_array_equal(np.asarray(root["s0"]), np.transpose(scan.mosaic, (2, 0, 1)))
    assert root.attrs["ome"]["multiscales"][0]["name"] == "mosaic"
    assert outputs.ZARR_ATTRS not in root.attrs  # the metadata writer's

    tiff_dir = tmp_path / "tiff"
    tiff_dir.mkdir()
    tiff = finished_scan(tiff_dir, MosaicFormat.OME_TIFF)
    assert MosaicWriter().write(tiff) == [tiff_dir / outputs.MOSAIC]
    with tifffile.TiffFile(tiff_dir / outputs.MOSAIC) as tif:
        assert tif.is_ome and "focustrack scan: kf-2d on sim/slide-0" in tif.ome_metadata
        np.testing.assert_array_equal(tif.series[0].asarray(), tiff.mosaic)
    assert OmeZarrMetadataWriter().write(tiff) == []  # an OME-TIFF has no such group


def test_the_ome_zarr_metadata_writer_adds_the_scan_and_its_maps(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    MosaicWriter().write(scan)
    assert OmeZarrMetadataWriter().write(scan) == [tmp_path / outputs.MOSAIC_ZARR]
    root = zarr.open_group(tmp_path / outputs.MOSAIC_ZARR, mode="r")
    attributes = root.attrs[outputs.ZARR_ATTRS]
    assert attributes["scan"] == {
        "strategy": "kf-2d",
        "instrument": "sim",
        "slide": "slide-0",
        "slide_id": "abc",
    }
    assert attributes["tile_px"] == {"height": TILE_PX, "width": TILE_PX}
    tiles = {(tile["row"], tile["col"]): tile for tile in attributes["tiles"]}
    assert tiles[(0, 0)]["best_z_um"] == 10.4 and tiles[(0, 0)]["flags"] == ["ambiguous"]
    assert tiles[(1, 2)]["planes_um"] == [8.5, 9.0] and tiles[(1, 2)]["images"] == 9
    assert tiles[(0, 1)]["z_used_um"] is None and tiles[(0, 1)]["best_z_um"] is None
    maps = root[outputs.ZARR_MAPS]
    np.testing.assert_array_equal(
        np.asarray(maps["posterior_um"]["s0"]), scan.focus_map.posterior_um
    )
    np.testing.assert_array_equal(np.asarray(maps["images"]["s0"]), scan.images_per_tile)


def test_the_report_writer_writes_the_scans_report(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    (path,) = ReportWriter().write(scan)
    assert json.loads(path.read_text()) == {"strategy": "kf-2d", "mosaic": outputs.MOSAIC_ZARR}


def test_a_scan_without_a_mosaic_writes_none_and_no_preview(tmp_path: Path) -> None:
    scan = replace(finished_scan(tmp_path), mosaic=None)
    for writer in (MosaicWriter(), MosaicPreviewWriter(), OmeZarrMetadataWriter()):
        assert writer.write(scan) == []
    assert sorted(path.name for path in tmp_path.iterdir()) == [outputs.PARTIAL_MOSAIC]


class PhaseLayerWriter:
    """A new output: the writers' list is all a scan needs to know of it."""

    def __init__(self) -> None:
        self.seen: list[FinishedScan] = []

    def write(self, scan: FinishedScan) -> list[Path]:
        self.seen.append(scan)
        path = scan.out_dir / "phase.npy"
        np.save(path, scan.focus_map.posterior_um)
        return [path]


def test_an_added_writer_is_called_with_the_scan_after_the_default_ones(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    phase = PhaseLayerWriter()
    written = write_outputs(scan, (*DEFAULT_WRITERS, phase))
    assert phase.seen == [scan]
    assert written[-1] == tmp_path / "phase.npy" and (tmp_path / "phase.npy").exists()
    names = {path.name for path in written}
    assert names == {
        outputs.FOCUS_MAP_CSV, outputs.FOCUS_MAP_NPY, outputs.PLOTS, outputs.MOSAIC_PREVIEW,
        outputs.MOSAIC_ZARR, outputs.REPORT, "phase.npy",
    }  # fmt: skip
    assert set(names) <= {path.name for path in tmp_path.iterdir()}
    assert not (tmp_path / outputs.PARTIAL_MOSAIC).exists()  # the mosaic file replaced it


class FailingWriter:
    def write(self, scan: FinishedScan) -> list[Path]:
        raise OSError("disk full")


def test_a_writer_that_fails_leaves_the_partial_mosaic_for_a_second_try(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    with pytest.raises(OSError, match="disk full"):
        write_outputs(scan, (MosaicWriter(), FailingWriter(), OmeZarrMetadataWriter()))
    assert (tmp_path / outputs.PARTIAL_MOSAIC).exists()
    written = write_outputs(finished_scan(tmp_path), DEFAULT_WRITERS)  # the scan run again
    assert tmp_path / outputs.MOSAIC_ZARR in written
    assert outputs.ZARR_ATTRS in zarr.open_group(tmp_path / outputs.MOSAIC_ZARR, mode="r").attrs
    assert not (tmp_path / outputs.PARTIAL_MOSAIC).exists()


def test_writers_without_the_mosaic_keep_the_partial_mosaic(tmp_path: Path) -> None:
    write_outputs(finished_scan(tmp_path), (ReportWriter(),))
    assert (tmp_path / outputs.PARTIAL_MOSAIC).exists()


def test_a_finished_scan_does_not_change(tmp_path: Path) -> None:
    scan = finished_scan(tmp_path)
    with pytest.raises(TypeError):
        scan.kept[(0, 1)] = 1.0  # type: ignore[index]
    with pytest.raises(AttributeError):
        scan.dof_um = 2.0  # type: ignore[misc]
