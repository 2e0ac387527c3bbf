"""The filter's FFTs: unitary (the paper's K, K K^H = U), single precision, in place, on
working images whose rows are padded.

Why padded: a row of 2048 complex64 pixels is 16 KiB, a multiple of the L1 cache's 4 KiB
way, so the column pass of an FFT over an unpadded image (a column's pixels, each a row
apart) maps them all to one cache set, which evicts itself. With every row 8 pixels
longer, a 2048 x 2048 complex64 FFT takes 25-27 ms of CPU here instead of 38-47 ms
(docs/benchmarks.md). One pad in pixels for every dtype keeps a complex and a float32
working image's pixels at the same flat index, so element-wise passes run over whole
contiguous buffers, padding included (numpy's passes over a strided view take about twice
as long); the padding starts at zero and stays finite.
"""

from __future__ import annotations

import numpy as np
from scipy import fft

ROW_PAD_PX = 8


def padded_zeros(shape: tuple[int, int], dtype: type[np.generic]) -> np.ndarray:
    """A working image: zeros of shape (height, width + ROW_PAD_PX), its image proper the
    first `width` columns."""
    return np.zeros((shape[0], shape[1] + ROW_PAD_PX), dtype=dtype)


def padded_image(shape: tuple[int, int], dtype: type[np.generic]) -> np.ndarray:
    """Zeros of `shape` (height, width) in a padded buffer (`padded_zeros`): the view of
    its image proper, whose FFTs run at the padded speed."""
    return padded_zeros(shape, dtype)[:, : shape[1]]


def fft2(image: np.ndarray, workers: int = 1) -> np.ndarray:
    """The unitary FFT of a complex64 image (height, width), in place (a strided view
    too); returns image."""
    return _in_place(image, fft.fft2(image, norm="ortho", workers=workers, overwrite_x=True))


def ifft2(image: np.ndarray, workers: int = 1) -> np.ndarray:
    """The unitary inverse FFT of a complex64 image (height, width), in place (a strided
    view too); returns image."""
    return _in_place(image, fft.ifft2(image, norm="ortho", workers=workers, overwrite_x=True))


def real_fft2(image: np.ndarray, out: np.ndarray, workers: int = 1) -> np.ndarray:
    """The unitary FFT of a real float32 image (height, width), written into the complex64
    `out` of the same shape and returned: rfft2 computes the bins with fx >= 0 for about
    half a complex FFT's time, and a real image's spectrum gives the others,
    F(-fy, -fx) = F(fy, fx)^*."""
    half = fft.rfft2(image, norm="ortho", workers=workers)
    width = image.shape[1]
    columns = half.shape[1]  # width // 2 + 1
    out[:, :columns] = half
    # Bin (row, col) with col >= columns is bin (-row, width - col) conjugated: the half's
    # columns width - columns .. 1 reversed, its rows 0 then height - 1 .. 1.
    mirrored = half[:, width - columns : 0 : -1]
    np.conjugate(mirrored[:1], out=out[:1, columns:])
    np.conjugate(mirrored[:0:-1], out=out[1:, columns:])
    return out


def _in_place(image: np.ndarray, transformed: np.ndarray) -> np.ndarray:
    # scipy.fft writes into a complex64 image it may overwrite; should a version not, the
    # working image must still hold the result.
    if transformed.ctypes.data != image.ctypes.data:
        np.copyto(image, transformed)
    return image
