"""The filter's FFTs: unnormalised, single precision, in place, on working images whose
rows are padded; OpenCV's DFT where it is installed, scipy.fft (pocketfft) otherwise.

Unnormalised both ways: `dft2` is sum_x a(x) e^{-2 pi i f.x}, `idft2` the same sum with
e^{+2 pi i f.x} and no 1/N, so `idft2(dft2(a)) = N a` for an image of N pixels. The
filter folds the 1/N and the unitary FFT's 1/sqrt(N) (the paper's K) into products it
takes anyway (H, the gain), which saves a pass over the image per transform.

Why padded: a row of 2048 complex64 pixels is 16 KiB, a multiple of the L1 cache's 4 KiB
way, so the column pass of an FFT over an unpadded image (a column's pixels, each a row
apart) maps them all to one cache set, which evicts itself. With every row 8 pixels
longer, a 2048 x 2048 complex64 FFT takes 23-27 ms of CPU here instead of 37-47 ms with
scipy.fft, 13.5-14 ms instead of 21-22 ms with OpenCV (docs/benchmarks.md). One pad in
pixels for every dtype keeps a complex and a float32 working image's pixels at the same
flat index, so element-wise passes run over whole contiguous buffers, padding included
(numpy's passes over a strided view take about twice as long); the padding starts at zero
and stays finite.

Why OpenCV: its DFT takes a padded 2048 x 2048 complex64 image in 13.5-17 ms of CPU
against pocketfft's 23-27 ms, and a real image in 6.5 ms (packed "CCS" spectrum) against
rfft2's 12.5-15.6 ms (docs/benchmarks.md). OpenCV is an accelerator, not a dependency, as
for the focus maths (`focustrack_focus.filters`): the phase service installs it (extra
`service`), and both backends give the same numbers to single precision's round-off
(`services/phase/tests/test_phase.py` checks them against each other). scipy.fft serves
when OpenCV is missing, when a transform is to run on several threads (OpenCV's DFT of
one image runs on one), and for sizes with a prime factor above 5, where OpenCV's DFT
has no fast algorithm.
"""

from __future__ import annotations

import importlib
from types import ModuleType

import numpy as np
from scipy import fft

from focustrack_phase.propagation import FoldedGrid

ROW_PAD_PX = 8


def _opencv() -> ModuleType | None:
    try:
        return importlib.import_module("cv2")
    except ImportError:  # not installed, or installed without its system libraries (libGL)
        return None


#: OpenCV's module where it imports, else None (tests set None to compare the backends).
OPENCV: ModuleType | None = _opencv()


def padded_zeros(shape: tuple[int, int], dtype: type[np.generic]) -> np.ndarray:
    """A working image: zeros of shape (height, width + ROW_PAD_PX), its image proper the
    first `width` columns."""
    return np.zeros((shape[0], shape[1] + ROW_PAD_PX), dtype=dtype)


def padded_image(shape: tuple[int, int], dtype: type[np.generic]) -> np.ndarray:
    """Zeros of `shape` (height, width) in a padded buffer (`padded_zeros`): the view of
    its image proper, whose FFTs run at the padded speed."""
    return padded_zeros(shape, dtype)[:, : shape[1]]


def dft2(image: np.ndarray, workers: int = 1) -> np.ndarray:
    """The unnormalised DFT of a complex64 image (height, width), in place (a strided view
    too); returns image. `workers`: threads (scipy.fft's; OpenCV's only for 1)."""
    cv2 = _backend(image.shape, workers)
    if cv2 is not None:
        _opencv_dft(cv2, _channels(image), 0)
        return image
    return _in_place(image, fft.fft2(image, workers=workers, overwrite_x=True))


def idft2(image: np.ndarray, workers: int = 1) -> np.ndarray:
    """The unnormalised inverse DFT (no 1/N) of a complex64 image (height, width), in
    place (a strided view too); returns image."""
    cv2 = _backend(image.shape, workers)
    if cv2 is not None:
        _opencv_dft(cv2, _channels(image), cv2.DFT_INVERSE)
        return image
    return _in_place(image, fft.ifft2(image, norm="forward", workers=workers, overwrite_x=True))


def filter_real(
    image: np.ndarray,
    imaginary: np.ndarray,
    kernel: np.ndarray,
    grid: FoldedGrid,
    added: tuple[np.ndarray, np.ndarray] | None = None,
    workers: int = 1,
    workspace: np.ndarray | None = None,
) -> None:
    """A real image filtered by a kernel that depends on |f| alone: idft2(K dft2(image)).

    image: float32 (height, width), a strided view too; overwritten with the result's real
        part. imaginary: float32 of the same shape, overwritten with its imaginary part.
    kernel: K, complex64 on `grid`'s folded quarter.
    added: (x, m): a real float32 image of the same shape (spent) and a real quarter;
        dft2(image) + m dft2(x) is filtered instead.
    workspace: a complex64 image of the same shape the scipy path may overwrite (one is
        allocated otherwise).

    A real image's spectrum S is Hermitian (half of it gives the rest) and K(f) = K(-f).
    With OpenCV: Re(K) S and Im(K) S are Hermitian too, so each inverse is real: a real
    forward DFT into OpenCV's packed (CCS) spectrum, the kernel's two parts multiplied into
    it as it is, and two real inverses, about half a complex DFT each. scipy's real
    inverse (irfft2) costs a complex one, so with scipy the half spectrum is mirrored into
    a full one and taken back by one complex inverse.
    """
    cv2 = _backend(image.shape, workers)
    if cv2 is None:
        spectrum = np.empty(image.shape, np.complex64) if workspace is None else workspace
        _full_spectrum(image, spectrum, workers)
        if added is not None:
            added_spectrum = _full_spectrum(added[0], np.empty_like(spectrum), workers)
            grid.multiply(added_spectrum, added[1])
            spectrum += added_spectrum
        grid.multiply(spectrum, kernel)
        idft2(spectrum, workers)
        np.copyto(image, spectrum.real)
        np.copyto(imaginary, spectrum.imag)
        return
    _opencv_dft(cv2, image, 0)  # the packed (CCS) spectrum, in place
    if added is not None:
        _opencv_dft(cv2, added[0], 0)
        _multiply_packed(added[0], added[1], grid)
        image += added[0]
    np.copyto(imaginary, image)
    for part, kernel_part in zip((image, imaginary), (kernel.real, kernel.imag), strict=True):
        _multiply_packed(part, kernel_part, grid)
        _opencv_dft(cv2, part, cv2.DFT_INVERSE | cv2.DFT_REAL_OUTPUT)


def _full_spectrum(image: np.ndarray, out: np.ndarray, workers: int) -> np.ndarray:
    """dft2 of a real float32 image (height, width) written into the complex64 `out` of
    its shape, with scipy: rfft2 computes the bins with fx >= 0 for about half a complex
    FFT's time, and a real image's spectrum gives the others, F(-fy, -fx) = F(fy, fx)^*."""
    half = fft.rfft2(image, workers=workers)
    width = image.shape[1]
    columns = half.shape[1]  # width // 2 + 1
    out[:, :columns] = half
    # Bin (row, col) with col >= columns is bin (-row, width - col) conjugated: the half's
    # columns width - columns .. 1 reversed, its rows 0 then height - 1 .. 1.
    mirrored = half[:, width - columns : 0 : -1]
    np.conjugate(mirrored[:1], out=out[:1, columns:])
    np.conjugate(mirrored[:0:-1], out=out[1:, columns:])
    return out


def _multiply_packed(packed: np.ndarray, quarter: np.ndarray, grid: FoldedGrid) -> None:
    """OpenCV's packed (CCS) spectrum of a real image (float32 (height, width)) times a
    real quarter (`grid`'s), in place.

    CCS: columns 1 .. 2 pairs hold the bins kx = 1 .. pairs of every row as (Re, Im)
    pairs; column 0 (and the last column, kx = width / 2, for an even width) holds a real
    column's spectrum packed along the rows: Re F(0), then (Re, Im) of F(1) .. and, for an
    even height, Re F(height / 2); row i holds bin |ky| = (i + 1) // 2.
    """
    height, width = packed.shape
    pairs = (width - 1) // 2
    grid.multiply(packed[:, 1 : 1 + 2 * pairs].view(np.complex64), quarter[:, 1 : 1 + pairs])
    rows = (np.arange(height) + 1) // 2
    packed[:, 0] *= quarter[rows, 0]
    if width % 2 == 0:
        packed[:, -1] *= quarter[rows, width // 2]


def _backend(shape: tuple[int, ...], workers: int) -> ModuleType | None:
    """OpenCV's module when it is to compute this transform, else None (scipy.fft)."""
    if OPENCV is None or workers != 1:
        return None
    return OPENCV if all(OPENCV.getOptimalDFTSize(n) == n for n in shape) else None


def _opencv_dft(cv2: ModuleType, array: np.ndarray, flags: int) -> None:
    """cv2.dft of a float32 array (height, width), or (height, width, 2) for a complex
    one, written into it."""
    _in_place(array, cv2.dft(array, dst=array, flags=flags))


def _channels(image: np.ndarray) -> np.ndarray:
    """A complex64 image (height, width) as the float32 (height, width, 2) view OpenCV
    takes for two channels."""
    return image.view(np.float32).reshape(*image.shape, 2)


def _in_place(image: np.ndarray, transformed: np.ndarray) -> np.ndarray:
    # scipy.fft writes into a complex64 image it may overwrite, OpenCV into a `dst` whose
    # memory it wraps; should a version copy a strided view instead, the working image
    # must still hold the result.
    if transformed.ctypes.data != image.ctypes.data:
        np.copyto(image, transformed)
    return image
