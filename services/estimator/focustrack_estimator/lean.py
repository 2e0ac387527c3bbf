"""How many frames a tile needs: none beyond the kept image, a short stack of 3, or a full stack.

The kept image is the only frame a user wants; every other frame costs
exposure, stage settling and photobleaching. So per tile the filter's
predicted Gaussian N(m, P) decides (`choose_stack`), with the risk of an
out-of-focus tile stated as a setting `risk` (0.01: at most 1% of tiles
outside the depth of field):

- the risk of a tile imaged at z_kept is P(|z_true - z_kept| > dof/2) under
  its Gaussian (`out_of_focus_risk`);
- one frame at m (the kept image, no measurement) when that risk is within
  `risk`, computed with the prediction's sigma widened by `skip_sigma_scale`
  (`skip_risk`): 2 Phi(-dof / (2 s sqrt(P))). A filter's sigma holds on
  measured tiles (kf-2d at 0.1 um noise: 0.8% of prior errors beyond 3 sigma)
  but not on runs of skipped ones, whose prior errors have heavy tails (2.9%
  beyond 3 sigma, std 1.21 sigma): skipped on the Gaussian's word they were out
  of focus 5 times as often as stated. Yet on the training seeds (0, 4 maps
  of each family) a scale of 1 kept every family within the stated 1%
  (docs/lean.md), so that is the default; the benchmark's reliability table
  checks the calibration on other seeds. Where a bank of models predicts the
  tile, the risk is its members' mixture's, tempered (`mixture_skip_risk`,
  `SKIP_MODEL_TEMPERATURE`): at low noise a bank that trusts its best member
  after a row missed 10 times as often as it stated. The tile is then a missing measurement
  for the filter (predict only), so the next tile's prior is wider: the rule
  measures again as soon as the sigma that grew over unmeasured tiles takes
  the risk past the setting;
- otherwise the tile is measured, with whichever of the short stack (3 frames
  one z step apart around m) and the policy's full stack
  (`ZRangePolicy.around`) costs fewer frames in expectation (`search_cost`):
  a stack whose range misses the measured peak is followed by the retry
  policy's stacks (`PeakSearch`), each taken with the probability that the
  innovation, N(0, P + R), lies beyond what was reached before it. A start
  whose retries would still miss the peak with a probability above `risk` is
  not an option (the tile would be given up); where neither is, the full stack.
  Both image the tile at the acquired frame nearest the posterior, so their
  risk is the same; where even a measured tile cannot meet `risk` (a
  measurement noise comparable to the depth of field) the tile is measured
  all the same, and the frames it keeps (below) bring the risk down; the
  benchmark's reliability table shows the risk achieved;
- once a measured tile's estimate is final and its kept frame alone is still
  above `risk`, it keeps more of its frames, each within a depth of field of the
  next, and is in focus when one of them is (`kept_planes`, `planes_risk`); the
  frames its stacks lack are acquired first (`planes_stack`).

Pure: numbers in, a `ZRange` out. Heights in um, variances in um^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from focustrack_core.domain import (
    CURVE_LEARN_FRAMES,
    PAIR_FRAMES,
    PAIR_REACH_UM,
    ZRange,
    ZRangePolicy,
)

#: Frames of a short stack: the fewest that locate a peak of known shape (curve_model).
SHORT_FRAMES = 3

#: z step of the coarse search, um: at most the focus curve's full width at half maximum,
#: so that one frame always lies above half the peak. The simulator's gradient metrics are
#: 4.6 um wide; a real whole-slide scanner's Brenner curves 3.5-6 um (wsi_focus_curves).
#: A narrower curve needs `coarse_step_um` set below its width.
COARSE_STEP_UM = 4.0

#: The power 1/T on a bank's member likelihoods for the risk of a tile imaged unmeasured
#: (`mixture_skip_risk` with `bank.tempered_weights`). After a row or two the bank's own
#: weights rest on one member, and where no member is the slide's (a smoothed exponential
#: field fits the smoothest members along a row, and decorrelates faster beyond it) that
#: member's narrow prediction, trusted over runs of unmeasured tiles, missed 10 times as
#: often as it stated: 41 misses against 3.7 stated on the simulator's standard 10x10 maps
#: at 0.03 um of noise (seeds 1000-1029, `estimator.replay`). Tempered, the weights keep
#: the members the data have not ruled out (a power posterior): T = 3 gave 2 misses
#: against 4.7 stated there, and on other seeds of four families (1030-1059: standard,
#: tilted, steps, rough) 2, 0, 3 and 3 against 4.8, 6.1, 3.8 and 1.8, at 2-9 % more
#: frames; T = 2 left 11 misses on the standard maps, T = 5 cost 5-14 % more frames
#: (docs/lean.md).
SKIP_MODEL_TEMPERATURE = 3.0


def out_of_focus_risk(
    mean_um: np.ndarray | float,
    sigma_um: np.ndarray | float,
    z_kept_um: np.ndarray | float,
    dof_um: float,
) -> np.ndarray:
    """P(|z - z_kept| > dof/2) for z ~ N(mean, sigma^2); any broadcastable shapes, in um.

    A sigma of 0 gives 0 or 1 (the kept frame is in focus or not for certain).
    """
    half_um = dof_um / 2.0
    mean, kept = np.asarray(mean_um, dtype=float), np.asarray(z_kept_um, dtype=float)
    sigma = np.maximum(np.asarray(sigma_um, dtype=float), 1e-12)
    inside = ndtr((kept + half_um - mean) / sigma) - ndtr((kept - half_um - mean) / sigma)
    return np.clip(1.0 - inside, 0.0, 1.0)


def skip_risk(sigma_um: float, dof_um: float, sigma_scale: float) -> float:
    """The risk of imaging a tile at its prediction (std `sigma_um`, widened by
    `sigma_scale`) without measuring it: 2 Phi(-dof / (2 sigma_scale sigma))."""
    return 2.0 * float(ndtr(-dof_um / 2.0 / max(sigma_scale * sigma_um, 1e-12)))


def mixture_skip_risk(
    means_um: np.ndarray,
    vars_um2: np.ndarray,
    weights: np.ndarray,
    z_kept_um: float,
    dof_um: float,
    sigma_scale: float,
) -> float:
    """The risk of imaging a tile at `z_kept_um` without measuring it where its prediction
    is a mixture of Gaussians (a bank's members: N(means_um[i], vars_um2[i]) with
    probability weights[i], summing to 1; shapes (n_members,)): each member's mass
    outside the depth of field there, weighted; each sigma widened by `sigma_scale`.

    Not the risk of the Gaussian with the mixture's mean and variance: where the members
    disagree on the variance the two part in the tails, which is all the risk reads.
    Members of 0.08 and 0.2 um weighted 3 to 1 have the variance of a Gaussian of 0.12
    um, which puts a tile half a depth of field of 0.89 um off at a risk of 0.03 %; the
    mixture at 0.66 %.
    """
    sigmas_um = sigma_scale * np.sqrt(np.maximum(np.asarray(vars_um2, dtype=float), 0.0))
    member_risks = out_of_focus_risk(means_um, sigmas_um, z_kept_um, dof_um)
    return float(np.asarray(weights, dtype=float) @ member_risks)


@dataclass(frozen=True)
class StackChoice:
    """What to acquire on a tile: the frames, whether they are measured, and why."""

    z: ZRange
    measure: bool
    skip_risk: float  # the risk of imaging the tile at its prediction without measuring
    expected_frames: float


def choose_stack(
    mean_um: float,
    var_um2: float,
    r_um2: float,
    dof_um: float,
    policy: ZRangePolicy,
    risk: float,
    if_skipped: float,
    max_retries: int,
    short_frames: int = SHORT_FRAMES,
) -> StackChoice:
    """The acquisition of a tile predicted at N(mean_um, var_um2); see the module docstring.

    `r_um2`: the variance expected of a measurement (the recent measurements' R);
    `risk`: the out-of-focus probability allowed for a tile, in (0, 1);
    `if_skipped`: the risk of imaging the tile at `mean_um` without measuring it (the
    filter's: `skip_risk` of its Gaussian, `mixture_skip_risk` of a bank's members);
    `max_retries`: the retries a search may take after its first stack (`PeakSearch`);
    `short_frames`: frames of the short stack, SHORT_FRAMES or PAIR_FRAMES (a pair reads
    peaks up to PAIR_REACH_UM beyond its frames, one more frame imaging them there:
    `frame_at_peak`).
    """
    if not 0.0 < risk < 1.0:
        raise ValueError(f"risk must lie in (0, 1), got {risk}")
    if if_skipped <= risk:
        return StackChoice(ZRangePolicy.single(mean_um, policy.z_step_um), False, if_skipped, 1.0)
    innovation_sigma_um = math.sqrt(max(var_um2, 0.0) + r_um2)
    full = policy.around(mean_um, innovation_sigma_um)
    short = ZRange.centred(mean_um, short_frames, policy.z_step_um)
    options = [
        (frames, z)
        for z in (short, full)
        if (frames := search_cost(z, innovation_sigma_um, policy, max_retries, risk, dof_um))
        is not None
    ]
    frames, z = min(options, key=lambda option: option[0], default=(math.nan, full))
    return StackChoice(z, True, if_skipped, frames)


def coarse_stack(
    mean_um: float, innovation_sigma_um: float, policy: ZRangePolicy, coarse_step_um: float
) -> ZRange | None:
    """A coarse search where the prediction is far too unsure for fine stacks, else None.

    Where +/- k_sigma innovation sigmas exceed a quarter of the widest fine stack
    (the first tile of a slide, whose start is 10 um unsure), that range is
    covered at `coarse_step_um` instead (a focus curve is several um wide, so a
    coarse stack still finds its peak): 21 frames instead of 41 plus a retry.
    The peak found there only centres a short stack on the same tile, which
    measures it and holds the kept image (`SerpentineFilter`).
    """
    reach_um = policy.k_sigma * innovation_sigma_um
    if reach_um <= policy.max_frames * policy.z_step_um / 4.0 or coarse_step_um <= policy.z_step_um:
        return None
    n_frames = min(2 * math.ceil(reach_um / coarse_step_um) + 1, policy.max_frames)
    return ZRange.centred(mean_um, n_frames, coarse_step_um)


def teaching_stack(mean_um: float, policy: ZRangePolicy, curve_width_um: float) -> ZRange:
    """Fine frames over +/- `curve_width_um` (the curve's full width at half maximum, at
    most) about `mean_um`: a stack whose curve teaches the focus service the slide's shape,
    both flanks and the background beside them (at least CURVE_LEARN_FRAMES frames, at most
    the policy's). A scan whose short stacks come back vague for want of that shape (the
    slide's first, on a focus service that has not seen the slide) takes one."""
    n_frames = 2 * math.ceil(curve_width_um / policy.z_step_um) + 1
    n_frames = min(max(n_frames, CURVE_LEARN_FRAMES), policy.max_frames)
    return ZRange.centred(mean_um, n_frames, policy.z_step_um)


def search_cost(
    z: ZRange,
    innovation_sigma_um: float,
    policy: ZRangePolicy,
    max_retries: int,
    risk: float,
    dof_um: float = 0.0,
) -> float | None:
    """Expected frames of a search that starts with `z`, None where it may end without a peak.

    The peak lies at an innovation y ~ N(0, innovation_sigma^2) from the centre. A
    miss is followed by the retry policy's blocks (`ZRangePolicy.beyond`: at least
    `min_frames`, each reaching (n - 2) z steps further); the k-th is taken when
    |y| lies beyond what the first stack and k - 1 retries reached. A start whose
    `max_retries` retries still miss the peak with a probability above `risk` (the
    tile is then given up, likely out of focus) is not an option. A pair (PAIR_FRAMES)
    reaches PAIR_REACH_UM beyond its frames, and takes one more frame where the peak
    lies beyond their depth of field (`dof_um`) there (`frame_at_peak`).
    """
    n_retry = max(z.n_frames, policy.min_frames)
    reach_um = (z.high_um - z.low_um) / 2.0
    frames = float(z.n_frames)
    if z.n_frames == PAIR_FRAMES:
        frames += 2.0 * float(ndtr(-(reach_um + dof_um / 2.0) / innovation_sigma_um))
        reach_um += PAIR_REACH_UM
    for _ in range(max_retries):
        p_miss = 2.0 * float(ndtr(-reach_um / innovation_sigma_um))
        frames += p_miss * n_retry
        reach_um += (n_retry - 2) * policy.z_step_um
    if 2.0 * float(ndtr(-reach_um / innovation_sigma_um)) > risk:
        return None
    return frames


def frame_at_peak(
    mean_um: float, sigma_um: float, dof_um: float, z_step_um: float, risk: float
) -> ZRange | None:
    """One frame at the posterior N(mean_um, sigma_um^2) of a tile whose frames do not hold
    its peak (a pair reads it up to PAIR_REACH_UM beyond them), where that frame alone is
    in focus within `risk`; None where it is not (the tile keeps planes instead)."""
    if float(out_of_focus_risk(mean_um, sigma_um, mean_um, dof_um)) > risk:
        return None
    return ZRangePolicy.single(mean_um, z_step_um)


def planes_risk(
    mean_um: float, sigma_um: float, planes_um: tuple[float, ...], dof_um: float
) -> float:
    """The risk of a tile kept at `planes_um` (at most a depth of field apart, sorted):
    P(z outside every plane's depth of field) for z ~ N(mean, sigma^2). Their windows
    join into one, from the lowest plane - dof/2 to the highest + dof/2."""
    low_um, high_um = planes_um[0], planes_um[-1]
    return float(
        out_of_focus_risk(mean_um, sigma_um, (low_um + high_um) / 2, high_um - low_um + dof_um)
    )


def kept_planes(
    mean_um: float,
    sigma_um: float,
    frames_um: np.ndarray,
    z_kept_um: float,
    dof_um: float,
    risk: float,
    max_planes: int,
) -> tuple[float, ...]:
    """The frames a tile keeps: `z_kept_um` alone where its risk is within `risk`, else
    the fewest acquired frames about it that bring the risk within `risk` (at most
    `max_planes`), sorted.

    Where one measurement is too noisy for the depth of field (the thesis' 1.5 um
    against 1 um), no single frame can be in focus with 99% certainty, but a few
    frames a depth of field apart can: the tile is in focus when one of them is.
    Greedily, each step adds the acquired frame (`frames_um`, any order) farthest
    below the lowest plane or above the highest, within a depth of field of it (so
    the windows join), whichever leaves the smaller risk (`planes_risk`). Frames
    come from the stacks already taken: a plane costs no exposure, only storage.
    """
    planes = [z_kept_um]
    while len(planes) < max_planes and planes_risk(mean_um, sigma_um, tuple(planes), dof_um) > risk:
        low_um, high_um = planes[0], planes[-1]
        below = frames_um[(frames_um < low_um) & (frames_um >= low_um - dof_um)]
        above = frames_um[(frames_um > high_um) & (frames_um <= high_um + dof_um)]
        options = [
            [float(below.min()), *planes] if below.size else None,
            [*planes, float(above.max())] if above.size else None,
        ]
        candidates = [option for option in options if option is not None]
        if not candidates:
            break
        planes = min(
            candidates, key=lambda option: planes_risk(mean_um, sigma_um, tuple(option), dof_um)
        )
    return tuple(planes)


def planes_stack(
    mean_um: float,
    sigma_um: float,
    z_kept_um: float,
    dof_um: float,
    z_step_um: float,
    risk: float,
    max_planes: int,
) -> ZRange | None:
    """Frames to acquire about `z_kept_um` where the tile's own stacks hold too few to keep
    (`kept_planes`): the fewest (odd, at most `max_planes`) a depth of field apart, or as
    near it as the z step allows, whose joined windows bring the risk within `risk`, else
    `max_planes` of them; None where one frame is enough or the z step exceeds the depth
    of field (frames that far apart leave gaps out of focus between them)."""
    step_um = math.floor(dof_um / z_step_um + 1e-9) * z_step_um
    if step_um <= 0 or max_planes < 3:
        return None

    def risk_of(n_frames: int) -> float:
        half_um = (n_frames - 1) / 2 * step_um
        return planes_risk(mean_um, sigma_um, (z_kept_um - half_um, z_kept_um + half_um), dof_um)

    n_frames = 1
    while risk_of(n_frames) > risk and n_frames + 2 <= max_planes:
        n_frames += 2
    return None if n_frames == 1 else ZRange.centred(z_kept_um, n_frames, step_um)


@dataclass(frozen=True)
class RiskSummary:
    """A scan's predicted out-of-focus risk over its imaged tiles, against the stated one.

    `expected_out_of_focus` is the mean of the tiles' predicted risks: the share of
    them expected outside the depth of field (a scan with the truth known can check
    it, as `focustrack bench accuracy`'s reliability table does). `note` says why the
    stated risk is not met, when it is not.
    """

    stated_risk: float | None  # the slide's `risk_out_of_focus`; None where it states none
    n_tiles: int  # imaged tiles with a predicted risk
    expected_out_of_focus: float
    n_over_stated: int  # tiles whose predicted risk exceeds the stated one
    note: str | None


def summarise_risk(
    risk: np.ndarray, stated_risk: float | None, dof_um: float, measurement_sigma_um: float
) -> RiskSummary | None:
    """The summary of a risk map (rows, cols; NaN where no tile was imaged), None if empty.

    `measurement_sigma_um` is the sigma the recent measurements had; beside the depth
    of field `dof_um` it tells a user why a stated risk cannot be met: where a
    single measurement is too noisy for the depth of field, even the measured tiles
    stay above it (thesis noise 1.5 um against a 1 um depth of field: about a third
    of tiles out of focus with one frame per tile, for any estimator).
    """
    imaged = risk[np.isfinite(risk)]
    if imaged.size == 0:
        return None
    expected = float(imaged.mean())
    over = 0 if stated_risk is None else int(np.count_nonzero(imaged > stated_risk))
    note = None
    if stated_risk is not None and expected > stated_risk:
        note = (
            f"the stated risk ({stated_risk:.1%}) is not met: {expected:.1%} of the "
            f"{imaged.size} imaged tiles are expected out of focus, and {over} tiles are above "
            f"it; measurements with a sigma of {measurement_sigma_um:.2g} um against a depth "
            f"of field of {dof_um:.2g} um leave even a measured tile that unsure: keep more "
            "frames per tile (max_kept_planes) or measure with a sharper focus metric"
        )
    return RiskSummary(stated_risk, int(imaged.size), expected, over, note)
