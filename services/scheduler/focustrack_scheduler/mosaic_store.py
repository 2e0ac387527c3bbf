"""The mosaic while it is filled in, and the frames a tile keeps besides its image.

``mosaic.partial.npy`` is a memory map of (rows * h, cols * w, channels) uint8: each tile's
image lands in its place as it is kept, so a restarted scheduler carries on with the
tiles already there. ``planes/r{row}_c{col}.npy`` holds a tile's kept frames as the camera
gave them; the tile's place in the mosaic then shows their fusion (`fusion.fuse_planes`).
``phase/r{row}_c{col}.npy`` holds a tile's phase and amplitude (with ``--phase``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from focustrack_core.fusion import fuse_planes
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.outputs import PARTIAL_MOSAIC, PHASE, PLANES, OutputFolderError


def to_uint8(frame: np.ndarray, bit_depth: int) -> np.ndarray:
    """A camera frame (h, w, channels) of `bit_depth` bits as 8 bits per channel."""
    scale = 255.0 / (2**bit_depth - 1)
    return np.clip(np.rint(frame * scale), 0, 255).astype(np.uint8)


class MosaicStore:
    """The partial mosaic and the planes files of the scan in `out_dir`."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = Path(out_dir)
        self.path = self.out_dir / PARTIAL_MOSAIC
        self._mosaic: np.memmap | None = None

    def write_tile(
        self, grid: ScanGrid, row: int, col: int, image: np.ndarray, bit_depth: int
    ) -> None:
        """Tile (row, col)'s image (h, w, channels) of `bit_depth` bits, in its place."""
        mosaic = self._open(grid, image.shape)
        height, width = image.shape[:2]
        mosaic[row * height : (row + 1) * height, col * width : (col + 1) * width] = to_uint8(
            image, bit_depth
        )

    def save_planes(
        self, grid: ScanGrid, row: int, col: int, frames: np.ndarray, bit_depth: int
    ) -> str:
        """Keep tile (row, col)'s `frames` (n, h, w, channels), ascending in z; its place in
        the mosaic becomes their fusion, each pixel from the sharpest. The file, relative to
        the output folder."""
        file = self._save_tile_array(PLANES, row, col, frames)
        self.write_tile(grid, row, col, fuse_planes(frames), bit_depth)
        return file

    def save_phase(self, row: int, col: int, field: np.ndarray) -> str:
        """Keep tile (row, col)'s phase and amplitude, float32 (2, h, w); the file, relative
        to the output folder."""
        return self._save_tile_array(PHASE, row, col, field)

    def _save_tile_array(self, folder_name: str, row: int, col: int, array: np.ndarray) -> str:
        """`array` as ``{folder_name}/r{row}_c{col}.npy``, written whole, then renamed
        (never half a file); the file, relative to the output folder."""
        folder = self.out_dir / folder_name
        folder.mkdir(exist_ok=True)
        path = folder / f"r{row}_c{col}.npy"
        temporary = path.with_suffix(".tmp")
        with temporary.open("wb") as file:
            np.save(file, array, allow_pickle=False)
        temporary.replace(path)
        return f"{folder_name}/{path.name}"

    def read(self) -> np.ndarray | None:
        """The mosaic so far, read-only and mapped from disk; None if no tile was kept."""
        if self._mosaic is not None:
            self._mosaic.flush()
        return np.load(self.path, mmap_mode="r") if self.path.exists() else None

    def tile(self, grid: ScanGrid, row: int, col: int) -> np.ndarray | None:
        """Tile (row, col)'s place in the mosaic (h, w, channels), uint8, a view of the memory
        map (zeros where nothing was kept yet); None before any tile was kept."""
        mosaic = self._mosaic
        if mosaic is None:  # nothing kept by this process yet: the tiles of an earlier run
            if not self.path.exists():
                return None
            self.check()
            mosaic = np.load(self.path, mmap_mode="r")
        height, width = mosaic.shape[0] // grid.rows, mosaic.shape[1] // grid.cols
        return mosaic[row * height : (row + 1) * height, col * width : (col + 1) * width]

    def check(self) -> None:
        """OutputFolderError unless the partial mosaic of an earlier run, if there is one, is
        whole: an .npy of uint8 (height, width, channels) whose file holds every byte its
        header promises. A file cut short would be mapped all the same, and writing a tile
        past its end kills the process (SIGBUS)."""
        if not self.path.exists():
            return
        try:
            with self.path.open("rb") as file:
                version = np.lib.format.read_magic(file)
                read_header = (
                    np.lib.format.read_array_header_1_0
                    if version == (1, 0)
                    else np.lib.format.read_array_header_2_0
                )
                shape, fortran_order, dtype = read_header(file)
                data_start = file.tell()
        except (OSError, ValueError) as error:
            raise self._damaged(f"its header cannot be read ({error})") from error
        if dtype != np.uint8 or len(shape) != 3 or fortran_order:
            raise self._damaged(f"it holds {dtype} {shape}, not uint8 (height, width, channels)")
        size = self.path.stat().st_size
        if (wanted := data_start + int(np.prod(shape))) != size:
            raise self._damaged(f"it has {size} bytes, where its header promises {wanted}")

    def _damaged(self, why: str) -> OutputFolderError:
        return OutputFolderError(
            f"{self.path} is damaged: {why}. The images of the tiles kept before are in it: "
            "move it away to carry on without them, or scan into a new output folder"
        )

    def _open(self, grid: ScanGrid, tile_shape: tuple[int, ...]) -> np.memmap:
        if self._mosaic is None:
            height, width, channels = tile_shape
            shape = (grid.rows * height, grid.cols * width, channels)
            if self.path.exists():
                self.check()
                self._mosaic = np.lib.format.open_memmap(self.path, mode="r+")
                if self._mosaic.shape != shape:
                    raise OutputFolderError(
                        f"{self.path} holds a {self._mosaic.shape} mosaic; tiles of "
                        f"{tile_shape} on a {grid.rows}x{grid.cols} grid need {shape}: use a "
                        "new output folder"
                    )
            else:
                self._mosaic = np.lib.format.open_memmap(
                    self.path, mode="w+", dtype=np.uint8, shape=shape
                )
        return self._mosaic

    def close(self) -> None:
        if self._mosaic is not None:
            self._mosaic.flush()
            self._mosaic = None
