"""A z-stack (or a curve of scores) in, a `FocusResult` out: one path for REST, Zenoh, bench."""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from focustrack_core.domain import MAX_ABS_Z_UM, PAIR_FRAMES, FocusFlag, Measurement, Prior
from focustrack_focus import filters
from focustrack_focus.agreement import agreed_peak, agreement_scores
from focustrack_focus.curve_model import (
    SHORT_MAX_FRAMES,
    CurveModel,
    as_modelled,
    fit_short_stack,
)
from focustrack_focus.layers import layers_sigma_um
from focustrack_focus.look import MIN_LOOK_SNR, look_snr
from focustrack_focus.metrics import DEFAULT_METRIC, METRICS, get_metric
from focustrack_focus.pair import read_pair
from focustrack_focus.peak import (
    PeakFit,
    PeakMode,
    PeakSettings,
    find_peak,
    peak_floor_sigma_um,
    validate_curve,
)
from focustrack_focus.preprocess import Preprocess
from focustrack_focus.structure import structure_snr


@dataclass(frozen=True)
class FocusSettings:
    """Everything that decides how a stack is read: preprocessing, metric, peak reading."""

    preprocess: Preprocess = field(default_factory=Preprocess)
    metric: str = DEFAULT_METRIC
    peak: PeakSettings = field(default_factory=PeakSettings)
    #: A stack whose through-focus change stands less than this many noise spreads
    #: above its pixel noise holds nothing to focus on: flat (`structure.structure_snr`).
    min_structure_snr: float = 10.0

    def __post_init__(self) -> None:
        get_metric(self.metric)  # fail early on an unknown name


@dataclass(frozen=True)
class FocusResult:
    """The focus of one stack: its curve, best z and sigma (um, None where none), flags.

    z_um and scores have shape (n,), sorted by z. compute_time_s is the wall time
    of metric and fit in seconds. best_z_um and sigma_um are this stack's
    measurement alone, never mixed with a prior (the estimator holds the prior and
    must not count it twice); where the request carried a prior, posterior_z_um and
    posterior_sigma_um are the two combined. runner_up_z_um and chosen_probability:
    `peak.PeakFit`.
    """

    z_um: np.ndarray
    scores: np.ndarray
    best_z_um: float | None
    sigma_um: float | None
    flags: frozenset[FocusFlag]
    metric: str
    compute_time_s: float
    runner_up_z_um: float | None = None
    chosen_probability: float | None = None
    posterior_z_um: float | None = None
    posterior_sigma_um: float | None = None

    def measurement(self) -> Measurement:
        """The result as the estimator's `Measurement` (no z for a flat curve)."""
        return Measurement(self.best_z_um, self.sigma_um, self.flags)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON types; flags sorted for a stable output."""
        return {
            "z_um": self.z_um.tolist(),
            "scores": self.scores.tolist(),
            "best_z_um": self.best_z_um,
            "sigma_um": self.sigma_um,
            "flags": sorted(str(flag) for flag in self.flags),
            "metric": self.metric,
            "compute_time_s": self.compute_time_s,
            "runner_up_z_um": self.runner_up_z_um,
            "chosen_probability": self.chosen_probability,
            "posterior_z_um": self.posterior_z_um,
            "posterior_sigma_um": self.posterior_sigma_um,
        }


@dataclass(frozen=True)
class StackScan:
    """The scores of a stack (n,) and the frames the structure test compares.

    sharpest, blurriest: preprocessed frames (h, w) float32 of the highest and
    lowest score; blurriest_raw: the raw 2-D crop (channel, ROI) of the latter.
    """

    scores: np.ndarray
    sharpest: np.ndarray
    blurriest: np.ndarray
    blurriest_raw: np.ndarray


def check_intensities(image: np.ndarray, index: int) -> None:
    """ValueError unless frame `index`, preprocessed to (h, w), holds intensities: a positive
    mean, or no light at all (every pixel 0, which every metric scores 0).

    The metrics are contrasts: they divide by a power of the frame's mean (`metrics`). A
    background-subtracted or signed frame has a mean near or below 0, and its scores are
    large and meaningless: a confident, wrong peak with no flag.
    """
    mean = filters.BACKEND.mean(image)
    if not mean > 0 and np.any(image):
        raise ValueError(
            f"frame {index} has a mean intensity of {mean:.4g}: the focus metrics take "
            "intensities (raw counts), not background-subtracted or signed frames"
        )


def scan_stack(frames: np.ndarray, settings: FocusSettings) -> StackScan:
    """Preprocess and score every frame of a stack (n, H, W) or (n, H, W, C), n >= 1;
    ValueError at the first frame that is not of intensities (`check_intensities`)."""
    metric, preprocess = get_metric(settings.metric), settings.preprocess
    scores = np.empty(len(frames), dtype=np.float64)
    top = low = 0
    for i, frame in enumerate(frames):
        raw = preprocess.crop(frame)
        image = preprocess.smooth(raw)
        check_intensities(image, i)
        scores[i] = metric(image)
        if i == 0 or scores[i] > scores[top]:
            top, sharpest = i, image
        if i == 0 or scores[i] < scores[low]:
            low, blurriest, blurriest_raw = i, image, raw
    return StackScan(scores, sharpest, blurriest, blurriest_raw)


def focus_scores(frames: np.ndarray, settings: FocusSettings) -> np.ndarray:
    """The metric of every frame of a stack (n, H, W) or (n, H, W, C) -> scores (n,)."""
    return scan_stack(frames, settings).scores


def focus_from_curve(
    z_um: np.ndarray,
    scores: np.ndarray,
    settings: FocusSettings,
    *,
    started_s: float | None = None,
    structure_snr: float = math.inf,
    prior: Prior | None = None,
    curve: CurveModel | None = None,
    beside_layers: bool = False,
) -> FocusResult:
    """Read a curve of scores (n,) at z_um (n,); `started_s` (perf_counter) times the whole job.

    `structure_snr` is the stack's structure test (`structure.structure_snr`), where
    there were images; below `settings.min_structure_snr` nothing is in view: the
    curve is flat and the field empty (no other stack of this tile would find a peak).
    `prior`: the estimator's belief (um); it weighs the choice between peaks and
    gives the posterior. `curve`: the slide's learnt curve; a short stack (at most
    SHORT_MAX_FRAMES frames) is read with it once it is ready (`curve_model`), and a top
    broader than its tops is two layers (`layers`: the sigma widens; sooner where the tile
    lies `beside_layers`, a tile read so).
    """
    started_s = time.perf_counter() if started_s is None else started_s
    z, s = validate_curve(z_um, scores)
    if structure_snr < settings.min_structure_snr:
        fit = PeakFit(None, None, frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}))
    else:
        fit = find_peak(z, s, settings.peak, prior)
        if curve is not None:  # the slide's curve reads the stack as it learnt it
            peak_z, peak_s = as_modelled(z, s, settings.peak.mode)
            if curve.ready and z.size <= SHORT_MAX_FRAMES:
                step_um = float(np.median(np.diff(z)))
                floor_um = peak_floor_sigma_um(step_um, settings.peak)
                fit = fit_short_stack(peak_z, peak_s, curve, fit, floor_sigma_um=floor_um)
            if fit.z_um is not None and fit.sigma_um is not None:
                # a top broader than the slide's: two layers (a fold), the vertex between them
                layers_um = layers_sigma_um(
                    curve.top_widths_um, peak_z, peak_s, fit.z_um, beside_layers=beside_layers
                )
                fit = replace(fit, sigma_um=math.hypot(fit.sigma_um, layers_um))
    return _answer(z, s, fit, settings, started_s, prior)


def _answer(
    z_um: np.ndarray,
    scores: np.ndarray,
    fit: PeakFit,
    settings: FocusSettings,
    started_s: float,
    prior: Prior | None,
) -> FocusResult:
    """The result of a curve (z (n,) ascending, scores (n,)) read as `fit`, with the
    posterior where there is a `prior`; its compute time counts from `started_s`."""
    posterior = fit.posterior(prior) if prior is not None else None
    return FocusResult(
        z_um=z_um,
        scores=scores,
        best_z_um=fit.z_um,
        sigma_um=fit.sigma_um,
        flags=fit.flags,
        metric=settings.metric,
        compute_time_s=time.perf_counter() - started_s,
        runner_up_z_um=fit.runner_up_z_um,
        chosen_probability=fit.chosen_probability,
        posterior_z_um=None if posterior is None else posterior[0],
        posterior_sigma_um=None if posterior is None else posterior[1],
    )


def check_z(z_um: np.ndarray, *, pairs: bool = False) -> None:
    """ValueError unless `z_um` (n,) is a stack's z: one frame (a look) or a curve's frames
    (`validate_curve`: at least 3, finite, ascending); with `pairs` (the slide's curve is
    learnt), two frames as well (a pair, `pair_result`)."""
    pair = pairs and z_um.size == PAIR_FRAMES and z_um[0] != z_um[1]
    if (z_um.size == 1 or pair) and np.all(np.abs(z_um) <= MAX_ABS_Z_UM):  # NaN fails too
        return
    validate_curve(z_um, np.zeros_like(z_um))


#: The edge a pair without the slide's curve points to: towards its higher frame.
_PAIR_EDGES = (FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH)


def pair_result(
    z_um: np.ndarray,
    scores: np.ndarray,
    snr: float,
    settings: FocusSettings,
    started_s: float,
    curve: CurveModel | None = None,
    prior: Prior | None = None,
) -> FocusResult:
    """The answer to a pair, two frames at z_um (2,) with their scores (2,): flat and empty
    where the structure test (`snr`) sees nothing in view; else the peak their scores' ratio
    gives with the slide's learnt curve (`pair.read_pair`), or without one an edge flag
    towards the higher frame as the curve reads it (`curve_model.as_modelled`: the lower one
    in valley mode; a retry continues that way)."""
    order = np.argsort(z_um)
    z, s = z_um[order], scores[order]
    peak_s = as_modelled(z, s, settings.peak.mode)[1]  # two frames: no valley to crop to
    if snr < settings.min_structure_snr:
        fit = PeakFit(None, None, frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}))
    elif curve is not None and curve.ready:
        floor_um = peak_floor_sigma_um(float(z[1] - z[0]), settings.peak)
        fit = read_pair(z, peak_s, curve, floor_sigma_um=floor_um)
    else:
        higher = int(np.argmax(peak_s))
        fit = PeakFit(float(z[higher]), None, frozenset({_PAIR_EDGES[higher]}))
    return _answer(z, s, fit, settings, started_s, prior)


def look_result(
    z_um: np.ndarray, scores: np.ndarray, snr: float, settings: FocusSettings, started_s: float
) -> FocusResult:
    """The answer to a look, one frame at z_um (1,) with its score (1,): no focus (one frame
    has no curve), and flat and empty where its test (`look_reading`, `snr`) sees nothing
    in view; no flag where it does (a stack there will find the focus)."""
    empty = snr < MIN_LOOK_SNR
    return FocusResult(
        z_um=z_um,
        scores=scores,
        best_z_um=None,
        sigma_um=None,
        flags=frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}) if empty else frozenset(),
        metric=settings.metric,
        compute_time_s=time.perf_counter() - started_s,
    )


def look_reading(region: np.ndarray, settings: FocusSettings) -> float:
    """A look's statistic (`look.look_snr`) of its frame's region (h, w) or (h, w, C): its
    stain, or in valley mode, as for unstained specimens, its brightness (they have no
    stain; `look` says why)."""
    return look_snr(region, brightness=settings.peak.mode is PeakMode.VALLEY)


#: How a stack's array is laid out, as the errors say it.
STACK_LAYOUT = "a stack is frames first, (n, H, W) or (n, H, W, C)"


def focus_stack(
    frames: np.ndarray, z_um: np.ndarray, settings: FocusSettings, prior: Prior | None = None
) -> FocusResult:
    """The focus of a z-stack: frames (n, H, W) or (n, H, W, C) taken at z_um (n,); one
    frame is a look (`look_result`)."""
    started_s = time.perf_counter()
    if frames.ndim not in (3, 4):
        raise ValueError(f"{STACK_LAYOUT}; got shape {frames.shape}")
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 1 or z.size != frames.shape[0]:
        raise ValueError(
            f"{frames.shape[0]} frames but {z.size} z values: one z per frame needed "
            f"({STACK_LAYOUT}; got shape {frames.shape})"
        )
    check_z(z)  # frame count and z values, before any pixel work
    if frames.dtype.kind not in "uif":
        raise ValueError(f"pixels must be integers or floats, got dtype {frames.dtype}")
    if frames.dtype.kind == "f" and not np.all(np.isfinite(frames)):
        raise ValueError("pixels must be finite (NaN or infinity found)")
    scan = scan_stack(frames, settings)
    if z.size == 1:
        snr = look_reading(settings.preprocess.region(frames[0]), settings)
        return look_result(z, scan.scores, snr, settings, started_s)
    snr = structure_snr(scan.sharpest, scan.blurriest, scan.blurriest_raw, settings.preprocess)
    result = focus_from_curve(
        z, scan.scores, settings, started_s=started_s, structure_snr=snr, prior=prior
    )
    if result.flags != {FocusFlag.FLAT}:
        return result
    preprocess = settings.preprocess
    scores = np.stack([agreement_scores(preprocess.smooth(preprocess.crop(f))) for f in frames])
    return unflattened(result, scores, settings, prior)


def unflattened(
    flat: FocusResult, agreement: np.ndarray, settings: FocusSettings, prior: Prior | None
) -> FocusResult:
    """A stack read `flat` by the contrast rule alone (`peak.find_peak`; a stack the
    structure test found `empty` holds nothing in view, and its frames' shared noise may
    make the metrics agree) read again without that rule where the metrics on its frames,
    `agreement` (n, len(METRICS)) of `agreement.agreement_scores`, agree on a peak
    (`agreement.agreed_peak`: a person sees one) and the reading lands within a frame of
    it; else `flat` as it is."""
    if settings.peak.min_relative_noise >= 1.0:
        return flat  # a metric turned off on this microscope (`PeakSettings`) stays off
    agreed = agreed_peak(dict(zip(METRICS, agreement.T, strict=True)))
    if agreed is None:
        return flat
    no_flat_rule = replace(settings, peak=replace(settings.peak, min_contrast=0.0, min_snr=0.0))
    again = focus_from_curve(flat.z_um, flat.scores, no_flat_rule, prior=prior)
    if again.best_z_um is None:
        return flat
    frame_um = float(np.max(np.diff(flat.z_um[max(agreed - 1, 0) : agreed + 2])))
    if abs(again.best_z_um - float(flat.z_um[agreed])) > frame_um:
        return flat
    return replace(again, compute_time_s=flat.compute_time_s)


def _memory_of(array: np.ndarray) -> Any:
    """What owns `array`'s memory: the array itself, or the array or bytes it views."""
    owner: Any = array
    while isinstance(owner, np.ndarray) and owner.base is not None:
        owner = owner.base
    return owner


class FrameByFrame:
    """`focus_stack` built one frame at a time, as frames arrive, so the work overlaps
    acquisition: `add` scores a frame (preprocess and metric, as `scan_stack`); once
    every frame is in, `result` only reads the curve (structure test and peak fit).

    z_um (n,): the z of every frame of the stack, um (one frame: a look, `look_result`; with
    `pairs`, two frames: a pair, `pair_result`). Frames may come in any order;
    each is (H, W) or (H, W, C). `result` gives what `focus_stack` gives for the whole
    stack; its compute_time_s is the time spent in `add` and `result` together.
    """

    def __init__(self, z_um: np.ndarray, settings: FocusSettings, *, pairs: bool = False) -> None:
        self.z_um = np.asarray(z_um, dtype=np.float64)
        if self.z_um.ndim != 1:
            raise ValueError(f"z_um must be one z per frame, shape (n,), got {self.z_um.shape}")
        check_z(self.z_um, pairs=pairs)  # frame count and z values
        self.settings = settings
        self.scores = np.full(self.z_um.size, np.nan)
        self._agreement = np.full((self.z_um.size, len(METRICS)), np.nan)
        self._metric = get_metric(settings.metric)
        self._top = self._low = -1
        self._sharpest = self._blurriest = self._blurriest_raw = np.empty(0, np.float32)
        self._look_snr = math.nan  # a look's statistic (`look_reading`), read as it comes
        self._busy_s = 0.0
        self._frame_shape: tuple[int, ...] = ()  # the first frame's

    @property
    def complete(self) -> bool:
        """True once every frame has been added."""
        return not np.isnan(self.scores).any()

    @property
    def held_bytes(self) -> int:
        """Bytes it holds: its curve, and the frames it keeps for `result` (the sharpest
        and blurriest images, and the whole buffer that the blurriest's raw crop views)."""
        kept = map(_memory_of, (self._sharpest, self._blurriest, self._blurriest_raw))
        buffers = {
            id(owner): owner.nbytes if isinstance(owner, np.ndarray) else memoryview(owner).nbytes
            for owner in kept
        }
        curves = self.z_um.nbytes + self.scores.nbytes + self._agreement.nbytes
        return curves + sum(buffers.values())

    def add(self, index: int, frame: np.ndarray) -> None:
        """Score frame `index` (H, W) or (H, W, C); ValueError for a bad or repeated frame, or
        one not of intensities (`check_intensities`)."""
        started_s = time.perf_counter()
        if not 0 <= index < self.scores.size:
            raise ValueError(f"frame {index} of a stack of {self.scores.size} frames")
        if not np.isnan(self.scores[index]):
            raise ValueError(f"frame {index} arrived twice")
        if frame.ndim not in (2, 3) or frame.dtype.kind not in "uif":
            raise ValueError(
                f"a frame is (H, W) or (H, W, C) of integers or floats, got {frame.shape} "
                f"{frame.dtype}"
            )
        if self._frame_shape and frame.shape != self._frame_shape:  # one curve, one field
            raise ValueError(
                f"frame {index} is {frame.shape}; the stack's first was {self._frame_shape}"
            )
        self._frame_shape = frame.shape
        if frame.dtype.kind == "f" and not np.all(np.isfinite(frame)):
            raise ValueError("pixels must be finite (NaN or infinity found)")
        preprocess = self.settings.preprocess
        raw = preprocess.crop(frame)
        image = preprocess.smooth(raw)
        check_intensities(image, index)
        score = self._metric(image)
        if not np.isfinite(score):  # pixels past float32 (1e307 as counts): NaN marks "to come"
            raise ValueError(
                f"frame {index} scores {score} with the focus metric: its values (up to "
                f"{float(np.max(frame)):.3g}) overflow the metric's float32 arithmetic"
            )
        if self.z_um.size == 1:  # a look reads every colour of its frame
            self._look_snr = look_reading(preprocess.region(frame), self.settings)
        self.scores[index] = score
        self._agreement[index] = agreement_scores(image)
        if self._top < 0 or score > self.scores[self._top]:
            self._top, self._sharpest = index, image
        if self._low < 0 or score < self.scores[self._low]:
            self._low, self._blurriest, self._blurriest_raw = index, image, raw
        self._busy_s += time.perf_counter() - started_s

    def result(
        self,
        curve: CurveModel | None = None,
        prior: Prior | None = None,
        *,
        beside_layers: bool = False,
    ) -> FocusResult:
        """The focus of the stack (a short one read with `curve`, where given and ready, and
        `beside_layers` as `focus_from_curve`; its peaks weighed with `prior`, where given);
        ValueError while frames are missing."""
        if not self.complete:
            missing = np.flatnonzero(np.isnan(self.scores)).tolist()
            raise ValueError(f"frames {missing} have not arrived")
        started_s = time.perf_counter() - self._busy_s
        if self.z_um.size == 1:
            return look_result(self.z_um, self.scores, self._look_snr, self.settings, started_s)
        snr = structure_snr(
            self._sharpest, self._blurriest, self._blurriest_raw, self.settings.preprocess
        )
        if self.z_um.size == PAIR_FRAMES:
            return pair_result(self.z_um, self.scores, snr, self.settings, started_s, curve, prior)
        result = focus_from_curve(
            self.z_um,
            self.scores,
            self.settings,
            started_s=started_s,
            structure_snr=snr,
            prior=prior,
            curve=curve,
            beside_layers=beside_layers,
        )
        if result.flags != {FocusFlag.FLAT}:
            return result
        return unflattened(result, self._agreement, self.settings, prior)

    def continued(self, z_um: np.ndarray, *, pairs: bool = False) -> FrameByFrame:
        """This look (one frame, added) as the first frame of a stack whose other frames lie
        at z_um (n,), um, one step above it and on (`continues`; with `pairs`, one frame
        makes a pair): they are added as frames 1..n of the curve it returns. Its frame was
        answered as a look already (its compute time counted there)."""
        if (
            self.z_um.size != 1
            or not self.complete
            or not continues(float(self.z_um[0]), z_um, pairs=pairs)
        ):
            raise ValueError(f"frames at {z_um.tolist()} do not continue a look at {self.z_um}")
        joined = FrameByFrame(np.concatenate([self.z_um, z_um]), self.settings, pairs=pairs)
        joined.scores[0], joined._agreement[0] = self.scores[0], self._agreement[0]
        joined._top = joined._low = 0
        joined._sharpest, joined._blurriest = self._sharpest, self._blurriest
        joined._blurriest_raw = self._blurriest_raw
        return joined


def continues(look_z_um: float, z_um: np.ndarray, *, pairs: bool = False) -> bool:
    """Whether frames at z_um (n,), um, continue a look at `look_z_um`: two at least (one,
    above it, with `pairs`: a pair), evenly stepped upwards, the first one step above the
    look (to 1 nm)."""
    if z_um.size < (PAIR_FRAMES - 1 if pairs else 2):
        return False
    steps_um = np.diff(np.concatenate([[look_z_um], z_um]))
    return bool(steps_um[0] > 0 and np.all(np.abs(steps_um - steps_um[0]) < 1e-3))


class LastLooks:
    """Each slide's last look (a tile's first frame, taken alone: is anything in view?),
    until the next stack of that slide arrives: where that stack is the rest of the look's
    (the same tile, its frames one step above the look's and on: `continues`), the look is
    its first frame (`FrameByFrame.continued`), so a tile whose look saw something costs no
    frame more than its stack. Holds one look per slide, of at most `slides` slides."""

    def __init__(self, slides: int) -> None:
        self.slides = slides
        self._last: OrderedDict[str, tuple[tuple[int, int], FrameByFrame]] = OrderedDict()

    @property
    def held_bytes(self) -> int:
        """Bytes the held looks keep (`FrameByFrame.held_bytes`)."""
        return sum(look.held_bytes for _, look in self._last.values())

    def keep(self, slide: str, tile: tuple[int, int], curve: FrameByFrame) -> None:
        """Hold `curve` as the slide's last look, if it is one (a single frame, added)."""
        if curve.z_um.size == 1 and curve.complete:
            self._last.pop(slide, None)
            self._last[slide] = (tile, curve)
            while len(self._last) > self.slides:
                self._last.popitem(last=False)

    def curve(
        self,
        slide: str,
        tile: tuple[int, int],
        z_um: np.ndarray,
        settings: FocusSettings,
        *,
        pairs: bool = False,
    ) -> FrameByFrame:
        """The curve of a stack at z_um (n,) of `tile` of `slide` whose first frame is
        arriving: the slide's last look continued by it where it is the rest of that look's
        stack, else its own (the look is let go either way; `pairs` as `FrameByFrame`'s)."""
        tile_and_look = self._last.pop(slide, None)
        if tile_and_look is not None:
            looked, look = tile_and_look
            if looked == tile and continues(float(look.z_um[0]), z_um, pairs=pairs):
                return look.continued(z_um, pairs=pairs)
        return FrameByFrame(z_um, settings, pairs=pairs)
