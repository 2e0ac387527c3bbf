"""The metrics' agreement (`agreement`): a stack read flat by the contrast rule where most
metrics, the noise-robust one included, peak on the same interior frame is read after all;
a stack whose brightness alone changes with z stays flat; on the real stacks
(../shared/data/real) no label inside a stack comes back flat, and every reading lies
within a frame of it or is flagged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.agreement import AGREEMENT_CROP_PX, agreed_peak, agreement_scores
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakSettings, find_peak
from focustrack_focus.pipeline import FocusSettings, FrameByFrame, focus_stack
from focustrack_focus.preprocess import Preprocess
from focustrack_focus.real_data import YEAST_FOCUS_PLANE, load_smear, load_yeast

REAL = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "real"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} is missing (its README)")
#: Flags that warn that a z is not an ordinary measurement.
WARNINGS = {
    FocusFlag.EDGE_LOW,
    FocusFlag.EDGE_HIGH,
    FocusFlag.MULTI_PEAK,
    FocusFlag.AMBIGUOUS,
    FocusFlag.VALLEY,
}


def bump(n: int, top: float, width: float, level: float = 1.0) -> np.ndarray:
    """A curve (n,) of frames 0 .. n-1: `level` plus a Gaussian bump at frame `top`."""
    frames = np.arange(n)
    return level + 0.01 * np.exp(-0.5 * ((frames - top) / width) ** 2)


def test_most_metrics_on_one_interior_frame_agree_noise_does_not() -> None:
    names = list(METRICS)
    peaks = dict(zip(names, [4.0, 4.2, 3.8, 4.4, 4.1, 3.6], strict=True))
    assert agreed_peak({m: bump(9, top, 2.0) for m, top in peaks.items()}) == 4
    # a maximum on an end frame is no peak inside the stack: too few left to agree
    ends = {m: bump(9, 8.0 if i < 3 else 4.0, 2.0) for i, m in enumerate(names)}
    assert agreed_peak(ends) is None
    # pure noise: each metric's maximum wherever its own noise puts it
    rng = np.random.default_rng(3)
    assert agreed_peak({m: 1.0 + 1e-3 * rng.standard_normal(25) for m in names}) is None
    # the light dims at frame 12: the noise-sensitive metrics rise there, Vollath's F4 not
    dim = {m: bump(25, 12.0, 1.5) for m in names}
    dim["vollath_f4"] = 1.0 + 1e-3 * np.random.default_rng(4).standard_normal(25)
    dim["vollath_f4"][20] += 0.01
    assert agreed_peak(dim) is None
    with pytest.raises(ValueError, match="same frames"):
        agreed_peak({"brenner": np.ones(5), "tenengrad": np.ones(6)})


def test_agreement_scores_every_metric_on_the_frames_centre() -> None:
    image = np.random.default_rng(1).random((300, 400)).astype(np.float32)
    scores = agreement_scores(image)
    assert scores.shape == (len(METRICS),)
    centre = image[86 : 86 + AGREEMENT_CROP_PX, 136 : 136 + AGREEMENT_CROP_PX]
    assert scores[list(METRICS).index("brenner")] == pytest.approx(METRICS["brenner"](centre))


def test_a_stack_read_flat_by_contrast_whose_metrics_agree_is_read(render) -> None:
    """Cells in focus at 0 um, read with a contrast rule far stricter than the default
    (nine tenths of the curve's level): the curve is flat by that rule, yet every metric on the
    frames peaks on the focus frame, as a person sees it. Read through the whole stack and
    frame by frame alike; a metric turned off on the microscope (a noise floor as large as
    the maximum, an unusable profile entry) stays flat whatever the others say."""
    z_um = np.arange(-3.0, 3.01, 1.0)
    frames = render(96, z_um, 0.0, 11)
    strict = FocusSettings(peak=PeakSettings(min_contrast=0.9))
    assert find_peak(z_um, focus_stack(frames, z_um, strict).scores, strict.peak).flags == {
        FocusFlag.FLAT
    }
    result = focus_stack(frames, z_um, strict)
    assert FocusFlag.FLAT not in result.flags, result.flags
    assert result.best_z_um is not None and abs(result.best_z_um) <= 1.0
    assert result.sigma_um is not None
    live = FrameByFrame(z_um, strict)
    for index in (3, 0, 6, 1, 5, 2, 4):
        live.add(index, frames[index])
    by_frame = live.result()
    assert (by_frame.best_z_um, by_frame.sigma_um, by_frame.flags) == (
        result.best_z_um,
        result.sigma_um,
        result.flags,
    )
    off = FocusSettings(peak=PeakSettings(min_relative_noise=1.0))
    assert focus_stack(frames, z_um, off).flags == {FocusFlag.FLAT}


@pytest.mark.parametrize("gain", ["ends dim", "middle dim", "wave"])
def test_a_stack_whose_brightness_alone_wanders_stays_flat(render, gain: str) -> None:
    """One field in focus at every z, its light dimming towards the ends, in the middle, or
    in waves (Micro-Manager's demo camera, a lamp): noise-sensitive metrics may rise
    together where it dims, but nothing comes into focus, and every metric reads flat."""
    z_um = np.linspace(-5.0, 5.0, 21)
    field = render(128, np.zeros(1), 0.0, 5)[0].astype(np.float64)
    light = {
        "ends dim": 1.0 / (1.0 + np.abs(z_um) / 2.0),
        "middle dim": 1.0 - 0.5 * np.exp(-0.5 * z_um**2),
        "wave": 0.6 + 0.3 * np.sin(1.3 * z_um),
    }[gain]
    rng = np.random.default_rng(6)
    stack = np.stack([rng.poisson(g * field) for g in light]).astype(np.uint16)
    for metric in METRICS:
        result = focus_stack(stack, z_um, FocusSettings(metric=metric))
        assert FocusFlag.FLAT in result.flags and result.best_z_um is None, metric


#: These small frames are not oversampled like a slide scanner's: a 1 px low-pass.
REAL_PREPROCESS = Preprocess(lowpass_sigma_px=1.0)


def windows_around(label: int, n_planes: int) -> list[np.ndarray]:
    """Every window of 5, 7, 9 planes spaced 1 or 2 that holds plane `label`."""
    out = []
    for n in (5, 7, 9):
        for k in (1, 2):
            for first in range(label - (n - 1) * k, label + 1):
                planes = first + k * np.arange(n)
                if planes[0] >= 0 and planes[-1] < n_planes and label in planes:
                    out.append(planes)
    return out


def within_a_frame_or_flagged(result, label_um: float, frame_um: float) -> bool:
    if result.flags & WARNINGS:
        return True
    return result.best_z_um is not None and abs(result.best_z_um - label_um) <= frame_um


@needs_real
@pytest.mark.parametrize("metric", list(METRICS))
def test_no_real_stack_holding_its_label_reads_flat(metric: str) -> None:
    """The smear (stained) in full and in every scanner window holding its labelled plane,
    and the unstained yeast in full: never flat, and within a frame of the label or flagged
    (the yeast's maximum is flagged a valley)."""
    settings = FocusSettings(REAL_PREPROCESS, metric)
    frames, plane = load_smear(REAL / "lip_smear_zstack")
    label = int(np.flatnonzero(plane == 0)[0])
    for planes in [np.arange(plane.size), *windows_around(label, plane.size)]:
        result = focus_stack(frames[planes], plane[planes], settings)
        assert FocusFlag.FLAT not in result.flags, planes
        step = float(np.median(np.diff(plane[planes])))
        assert within_a_frame_or_flagged(result, 0.0, step), (planes, result.best_z_um)
    frames, z_um = load_yeast(REAL / "yeast_brightfield_zstack")
    result = focus_stack(frames, z_um, settings)
    assert FocusFlag.FLAT not in result.flags
    assert within_a_frame_or_flagged(result, YEAST_FOCUS_PLANE * 0.3, 0.3)
