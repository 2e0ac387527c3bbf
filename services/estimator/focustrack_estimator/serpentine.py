"""The one per-tile loop every filter strategy runs: predict a tile, stack around it, correct.

A `SerpentineFilter` walks the grid in serpentine order. On each tile:

1. `_predict(tile)` gives the prior (the subclass's filter moves onto the tile);
2. the stack is taken over the prior +/- k innovation sigmas
   (`ZRangePolicy.around`, sigma = sqrt(prior variance + R)): the measured
   peak, not the truth, must land in it; with `risk_out_of_focus` set, the
   lean rule (`lean.choose_stack`) picks the kept image alone (no
   measurement: the tile is predicted only), a 3-frame stack or that stack;
3. a stack without a peak (an edge peak or a flat curve) is no measurement:
   the same tile is acquired again beyond that edge (`PeakSearch`); when the
   search ends without a peak the tile is given up (`gave_up`) and imaged at
   its prediction, so that a scan always ends;
4. a peak corrects the filter (`_correct`), with its variance widened where a second peak
   could be the focus (`peaks.between_peaks_var_um2`: multi_peak), unless the NIS gate rejects it
   (`gated`): with `gate_nis` > 0, a measurement whose normalised innovation
   squared exceeds it is an outlier (dust, a parasite in another plane) and
   the tile keeps its prediction, unless `gate_patience` measurements in a row
   were rejected before it, in which case the surface really moved (a fold, a
   step) and the measurement is taken after the height's variance is inflated
   by the squared innovation (`_inflate`);
5. the tile is imaged (`FocusMap.z_used_um`) at the acquired frame nearest its
   posterior, among all the stacks taken on it.

Empty glass (a stack the focus service flags `empty`: nothing in view) is given up at
once and leaves the surface as it was. Glass lies in regions (around the section, in its
holes), so a tile is first looked at where glass is at least half of what the scan has seen
beside it: one or more of its scanned neighbours (the eight tiles around it) were found
empty, and no more of them were found with something in view (`in_glass`); or where the
last two tiles the scan imaged were found empty (a row of glass along tissue). The look is
one frame at its prediction (`look_at`), which the focus service answers `empty` or not
(`focustrack_focus.look`). An empty look is the tile's image, one frame in all; otherwise
the tile's stack follows and the look's frame is one of its frames. A field found empty
alone among scanned tissue (a sparse field among others) does not make its neighbours look,
nor does glass two tiles away: a look that sees tissue costs its frame.

A second pass's scheduler compares a tile's one frame taken at its prediction (the kept
image, not measured) with the first pass's image of the tile (`focustrack_scheduler.
focus_check`); a frame it finds out of focus (`Measurement.frame_out_of_focus`) does not
finish the tile: the policy's stack about the prediction follows (`ZRangePolicy.around`, the
innovation's sigma), measured as any other, and the frame is one of the tile's frames.

With `adapt_r` the default R (for measurements without their own sigma) is
estimated online by covariance matching of the innovations (E[y^2] = H P H' +
R), as a running mean that starts from `R_PRIOR_COUNT` copies of the
configured value. The 1-D Kalman filters (`kalman_strategies`), their bank
(`bank`) and the 2-D filters (`spatial`) differ only in the three hooks.
Heights in um, variances in um^2.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import dataclass, replace

import numpy as np

from focustrack_core.domain import (
    CURVE_LEARN_FRAMES,
    CURVE_SPREAD_CURVES,
    PAIR_FRAMES,
    Acquisition,
    FocusFlag,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    ZRange,
)
from focustrack_core.geometry import Tile
from focustrack_estimator.filter_params import FilterParams, RetryParams
from focustrack_estimator.lean import (
    SHORT_FRAMES,
    choose_stack,
    coarse_stack,
    frame_at_peak,
    kept_planes,
    planes_risk,
    planes_stack,
    skip_risk,
    teaching_stack,
)
from focustrack_estimator.look_first import first_part, with_look
from focustrack_estimator.peaks import between_peaks_var_um2
from focustrack_estimator.strategy import PeakSearch, Strategy
from focustrack_estimator.time_state import ScanClock

#: How many measurements the configured default R counts as when `adapt_r` estimates it.
R_PRIOR_COUNT = 20

#: How many recent measurements' R give the R a lean stack expects (`expected_r_um2`).
RECENT_R_COUNT = 20

#: A tile is looked at first (one frame: is anything in view?) where at least this share of
#: its scanned neighbours (the eight around it) were found empty, and one at least: glass.
#: Chosen offline on the truth maps of virtual slides of seeds 1-4 against wider reaches and
#: other shares: a stack on glass costs about three frames more than a look, a look on
#: tissue one.
GLASS_SHARE = 0.5
#: ... or where this many tiles the scan imaged last were found empty: a row of glass along
#: tissue (each of its tiles has more tissue than glass beside it).
GLASS_IN_A_ROW = 2
#: Short stacks in a row whose peaks come with a sigma over half the depth of field that
#: show the focus service lacks the slide's curve (`SerpentineFilter._note_curve`): with the
#: curve, such a sigma is mostly one tile's (a peak far from its frames); without it, every
#: pair's (docs/lean.md, teaching stacks).
VAGUE_IN_A_ROW = 2


@dataclass(frozen=True)
class Gaussian:
    """A height estimate: mean in um and variance in um^2."""

    mean_um: float
    var_um2: float

    @property
    def sigma_um(self) -> float:
        return math.sqrt(max(self.var_um2, 0.0))


def look_at(z_um: float, step_um: float) -> ZRange:
    """A look: one frame at `z_um`, measured (the focus service says whether anything is in
    view: `focustrack_focus.look`)."""
    return ZRange.centred(z_um, 1, step_um)


def in_glass(empty: np.ndarray, scanned: np.ndarray, tile: Tile) -> bool:
    """Whether `tile` is to be looked at first: of its scanned neighbours (the eight around
    it), one at least and GLASS_SHARE at least were found empty.

    empty, scanned: (rows, cols) bool, tiles found empty and tiles done.
    """
    window = (
        slice(max(tile.row - 1, 0), tile.row + 2),
        slice(max(tile.col - 1, 0), tile.col + 2),
    )
    found_empty = int(empty[window].sum())
    return found_empty >= 1 and found_empty >= GLASS_SHARE * int(scanned[window].sum())


def is_pair(acquisition: Acquisition, look: ZRange | None) -> bool:
    """Whether `acquisition` is a pair (two measured frames: the lean rule's short stack with
    `short_frames` 2), alone or the rest of one after `look`, its tile's look (`look_first`)."""
    return acquisition.measure and with_look(look, acquisition.z).n_frames == PAIR_FRAMES


def is_look(acquisition: Acquisition) -> bool:
    """Whether `acquisition` is a look (one measured frame of a tile's first acquisition)."""
    return (
        acquisition.measure and acquisition.z.n_frames == 1 and acquisition.purpose == Purpose.SCAN
    )


@dataclass(frozen=True)
class PendingPlanes:
    """A measured tile waiting for the frames it keeps (`lean.planes_stack`): the stack to
    acquire, the stacks it had, and its final posterior and outcome."""

    z: ZRange
    stacks: tuple[ZRange, ...]
    posterior: Gaussian
    outcome: Outcome


class SerpentineFilter(Strategy):
    """A recursive estimator walking the serpentine, one prediction and one correction a tile.

    Subclasses implement `_predict` (the prior of the next tile) and `_correct`
    (take its measurement, or None when the tile gave none), and `_inflate`
    where they support gating with patience. `_finish` runs once after the
    last tile. `gave_up` and `gated` (rows, cols) mark tiles imaged at their
    prediction: no stack found a peak, or the gate rejected the measurement.
    """

    def __init__(self, settings: SlideSettings, params: RetryParams) -> None:
        super().__init__(settings)
        self.options = FilterParams.of(params)
        self.gave_up = np.zeros(self.grid.shape, dtype=bool)
        self.gated = np.zeros(self.grid.shape, dtype=bool)
        self._position = 0  # serpentine index of the current tile
        self._prior: Gaussian | None = None  # the current tile's prior, once predicted
        self._search = PeakSearch(settings.policy, self.options.max_retries)  # current tile
        self._rejected_in_a_row = 0
        self._r_sum_um2 = R_PRIOR_COUNT * settings.noise_sigma_um**2
        self._r_count = R_PRIOR_COUNT
        self._innovation_um: list[float] = []
        self._innovation_var_um2: list[float] = []
        self._recent_r_um2: list[float] = []  # the R of the last RECENT_R_COUNT measurements
        self._skip_risk = math.nan  # the current tile's risk if imaged at its prediction
        self._centre_um: float | None = None  # a coarse stack's peak on the current tile
        self._planes: PendingPlanes | None = None  # frames the current tile still needs
        self.empty = np.zeros(self.grid.shape, dtype=bool)  # tiles found empty (nothing in view)
        self.scanned = np.zeros(self.grid.shape, dtype=bool)  # tiles done
        self._look: ZRange | None = None  # the current tile's look, once it saw something
        self._blurred: ZRange | None = None  # its unmeasured frame, once found out of focus
        self.clock = ScanClock()  # the scan's time, for filters with a time state
        self._long_stacks = 0  # stacks measured that could teach the slide's curve
        self._vague_in_a_row = 0  # short stacks read with a sigma over half the depth of field

    @abstractmethod
    def _predict(self, tile: Tile) -> Gaussian:
        """Advance the state to `tile` (the next in serpentine order); return its prior."""

    @abstractmethod
    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        """Take the measurement of `tile` (None: no measurement); return its posterior."""

    def _inflate(self, var_um2: float) -> None:
        """Add `var_um2` to the current tile's height variance (gating with patience)."""
        raise ValueError(
            f"{self.name} cannot widen its state for a step the gate lets through: leave "
            "gate_nis at 0"
        )

    def _finish(self) -> None:
        """Called once when every tile has been imaged (for final-map work)."""

    def _unmeasured_risk(self, tile: Tile, prior: Gaussian) -> float:
        """The risk of imaging `tile` at its prediction `prior` without measuring it
        (`lean.skip_risk`; a bank of models weighs its members': `RowBankFilter`)."""
        return skip_risk(prior.sigma_um, self.settings.dof_um, self.options.skip_sigma_scale)

    @property
    def default_r_um2(self) -> float:
        """The variance of a measurement that comes without a sigma (estimated if `adapt_r`)."""
        if not self.options.adapt_r:
            return self.settings.noise_sigma_um**2
        # Single terms y^2 - H P H' may be negative; only the mean must stay positive.
        floor_um2 = 1e-2 * self.settings.noise_sigma_um**2
        return max(self._r_sum_um2 / self._r_count, floor_um2)

    @property
    def expected_r_um2(self) -> float:
        """The R a measurement is expected to have: the median of the recent ones' R.

        The focus service's sigma depends on the slide and the metric, not on the
        configured default, so the lean choice between stacks (`lean.choose_stack`)
        expects what the recent measurements had (the default R before any).
        """
        if not self._recent_r_um2:
            return self.default_r_um2
        return float(np.median(self._recent_r_um2))

    @property
    def stated_risk(self) -> float | None:
        return self.options.risk_out_of_focus or None

    @property
    def measurement_sigma_um(self) -> float:
        return math.sqrt(self.expected_r_um2)

    def _first_stack(self, tile: Tile, prior: Gaussian) -> tuple[ZRange, bool]:
        """The first acquisition of `tile` with this prior: its frames and whether to measure."""
        risk, policy = self.options.risk_out_of_focus, self.settings.policy
        if not risk or self._blurred is not None:  # a frame out of focus: measure the tile
            innovation_sigma_um = math.sqrt(prior.var_um2 + self.default_r_um2)
            return policy.around(prior.mean_um, innovation_sigma_um), True
        if self._centre_um is not None:  # a coarse stack's peak centres a short one
            return ZRange.centred(self._centre_um, SHORT_FRAMES, policy.z_step_um), True
        coarse = coarse_stack(
            prior.mean_um,
            math.sqrt(prior.var_um2 + self.expected_r_um2),
            policy,
            self.options.coarse_step_um,
        )
        if coarse is not None:
            return coarse, True
        choice = choose_stack(
            prior.mean_um,
            prior.var_um2,
            self.expected_r_um2,
            self.settings.dof_um,
            self.settings.policy,
            risk,
            self._unmeasured_risk(tile, prior),
            self.options.max_retries,
            self.options.short_frames,
        )
        self._skip_risk = choice.skip_risk
        wanted = self._vague_in_a_row >= VAGUE_IN_A_ROW
        if choice.measure and wanted and self._long_stacks < CURVE_SPREAD_CURVES:
            return teaching_stack(prior.mean_um, policy, self.options.coarse_step_um), True
        return choice.z, choice.measure

    def _note_curve(self, measured: ZRange, measurement: Measurement) -> None:
        """Whether the focus service knows the slide's curve, as its answers show. A stack of
        CURVE_LEARN_FRAMES frames or more can teach it; VAGUE_IN_A_ROW short stacks in a row
        whose peaks come with a sigma over half the depth of field (empty fields and edges
        not counted) ask for one (`lean.teaching_stack`) on the next tile the rule
        measures, up to CURVE_SPREAD_CURVES of them in a scan (what the service needs to
        know the curve's spread). A scan's first stacks teach it where the start is unsure
        (a coarse or a full stack); a sure start (the laser's) takes pairs, which a focus
        service new to the slide reads as edges (the retry's wide stack then teaches one
        curve), then with a default spread of the widths: a sigma of about a um each."""
        if FocusFlag.EMPTY in measurement.flags:
            return
        if measured.n_frames >= CURVE_LEARN_FRAMES:
            self._long_stacks += 1
            self._vague_in_a_row = 0
        elif (
            measured.n_frames >= PAIR_FRAMES
            and measured.step_um <= self.settings.policy.z_step_um  # not a coarse search
            and measurement.is_observation
        ):
            sigma_um = measurement.sigma_um  # None: the default R, as the filter's own
            vague = sigma_um is not None and sigma_um > self.settings.dof_um / 2.0
            self._vague_in_a_row = self._vague_in_a_row + 1 if vague else 0

    def _in_glass(self, tile: Tile) -> bool:
        """Whether `tile` is to be looked at first: glass beside it (`in_glass`), or the
        GLASS_IN_A_ROW tiles the scan imaged last were found empty (glass along its path)."""
        behind = self.grid.serpentine[max(self._position - GLASS_IN_A_ROW, 0) : self._position]
        along = len(behind) == GLASS_IN_A_ROW and all(self.empty[t.row, t.col] for t in behind)
        return along or in_glass(self.empty, self.scanned, tile)

    def innovations(self) -> tuple[np.ndarray, np.ndarray]:
        """Accepted innovations (n,) in um and their predicted variances S (n,) in um^2.

        In scan order, for `diagnostics.innovation_diagnostics` (gated-out
        measurements are not innovations of the filter: their NIS is in their Outcome).
        """
        return np.array(self._innovation_um), np.array(self._innovation_var_um2)

    def _plan(self) -> Acquisition | None:
        if self._position == self.grid.n_tiles:
            return None
        tile = self.grid.serpentine[self._position]
        if self._planes is not None:
            return self._acquisition(
                tile.row,
                tile.col,
                self._planes.z,
                Purpose.PLANES,
                measure=False,
                predicted_um=self._planes.posterior.mean_um,
                predicted_sigma_um=self._planes.posterior.sigma_um,
            )
        if self._prior is None:
            self._prior = self._predict(tile)
            self.map.prior_um[tile.row, tile.col] = self._prior.mean_um
            self.map.prior_sigma_um[tile.row, tile.col] = self._prior.sigma_um
        prior = self._prior
        measure = True
        if not self._search:
            (z, measure), purpose = self._first_stack(tile, prior), Purpose.SCAN
            if measure and self._blurred is None:  # a frame out of focus: its stack, whole
                if self.options.look_first and (part := first_part(z, self._look)) != z:
                    z = part  # a look that costs no frame where something is in view
                elif self._look is None and self._in_glass(tile):
                    z = look_at(prior.mean_um, self.settings.policy.z_step_um)
        else:
            z, purpose = self._search.next_range(), Purpose.RETRY
        return self._acquisition(
            tile.row,
            tile.col,
            z,
            purpose,
            measure=measure,
            predicted_um=prior.mean_um,
            predicted_sigma_um=prior.sigma_um,
        )

    def _planes_to_take(
        self,
        acquisition: Acquisition,
        posterior: Gaussian,
        z_used_um: float,
        planes_um: tuple[float, ...],
        risk: float,
    ) -> ZRange | None:
        """The frames to acquire so that the tile can keep enough of them about its kept
        frame at `z_used_um`, None if none."""
        stated = self.options.risk_out_of_focus
        if not stated or risk <= stated or acquisition.purpose == Purpose.PLANES:
            return None
        if is_pair(acquisition, self._look):
            # a pair places a peak beyond its frames: one more frame there, where that is
            # enough (`lean.frame_at_peak`)
            at_peak = frame_at_peak(
                posterior.mean_um,
                posterior.sigma_um,
                self.settings.dof_um,
                self.settings.policy.z_step_um,
                stated,
            )
            if at_peak is not None:
                return at_peak
        if len(planes_um) >= self.options.max_kept_planes:
            return None
        policy = self.settings.policy
        return planes_stack(
            posterior.mean_um,
            posterior.sigma_um,
            z_used_um,
            self.settings.dof_um,
            policy.z_step_um,
            stated,
            # a stack of planes is a stack: within the slide's own bound on one
            min(self.options.max_kept_planes, policy.max_frames),
        )

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        tile = Tile(acquisition.row, acquisition.col)
        self.clock.advance(self.grid, tile, acquisition.z.n_frames)
        if acquisition.purpose == Purpose.PLANES:
            assert self._planes is not None  # planned by _plan for the pending planes
            # image only: the measurement's innovation was the outcome before this one
            outcome = replace(self._planes.outcome, accepted=False, innovation_um=None, nis=None)
            return self._finish_tile(acquisition, outcome, self._planes.posterior)
        prior = self._prior
        assert prior is not None  # set by _plan for the pending acquisition
        outcome = Outcome(
            tile.row, tile.col, accepted=False, prior_um=prior.mean_um,
            prior_sigma_um=prior.sigma_um,
        )  # fmt: skip
        if (
            not acquisition.measure
            and measurement.frame_out_of_focus
            and acquisition.purpose == Purpose.SCAN
        ):
            self._blurred = acquisition.z  # a stack of the tile follows
            return outcome
        if not acquisition.measure:  # the kept image only: a missing measurement, predict only
            return self._finish_tile(acquisition, outcome, self._correct(tile, prior, None, 0.0))
        if self._look is None and is_look(acquisition) and FocusFlag.EMPTY not in measurement.flags:
            self._look = acquisition.z  # something is in view: the tile's stack follows
            return outcome
        # a first stack after a look at its lowest frame is read with that frame
        measured = with_look(None if self._search else self._look, acquisition.z)
        self._note_curve(measured, measurement)
        if acquisition.z.step_um > self.settings.policy.z_step_um and measurement.is_observation:
            # found, but too coarsely to image the tile or correct the filter: a short stack
            # centred there follows, and measures the tile
            self._centre_um = measurement.z_um
            return outcome
        if measurement.z_um is None or not measurement.is_observation:
            if self._search.failed(measured, measurement):
                return outcome  # another stack of this tile follows
            self.gave_up[tile.row, tile.col] = True
            # an empty field holds nothing to be in focus: no more of its frames are worth keeping
            empty = FocusFlag.EMPTY in measurement.flags
            self.empty[tile.row, tile.col] = empty
            posterior = self._correct(tile, prior, None, 0.0)
            return self._finish_tile(acquisition, outcome, posterior, keep_planes=not empty)

        R_um2 = self.default_r_um2 if measurement.sigma_um is None else measurement.sigma_um**2
        # a second peak that could be the focus widens R (the chosen peak's z is kept)
        R_um2 += between_peaks_var_um2(
            measurement, prior.mean_um, prior.var_um2 + R_um2, self.settings.policy.k_sigma
        )
        self._recent_r_um2 = [*self._recent_r_um2[1 - RECENT_R_COUNT :], R_um2]
        innovation_um = measurement.z_um - prior.mean_um
        variance_um2 = prior.var_um2 + R_um2
        outcome = replace(outcome, innovation_um=innovation_um, nis=innovation_um**2 / variance_um2)
        if self.options.gate_nis and innovation_um**2 / variance_um2 > self.options.gate_nis:
            if self._rejected_in_a_row < self.options.gate_patience:
                # An outlier: the tile keeps its prediction and is imaged there.
                self._rejected_in_a_row += 1
                self.gated[tile.row, tile.col] = True
                return self._finish_tile(
                    acquisition, outcome, self._correct(tile, prior, None, 0.0)
                )
            # Outliers in a row are the surface itself moving (a fold, a step): take it.
            self._inflate(innovation_um**2)
            variance_um2 += innovation_um**2
        self._rejected_in_a_row = 0
        posterior = self._correct(tile, prior, measurement.z_um, R_um2)
        if self.options.adapt_r and measurement.sigma_um is None:
            self._r_sum_um2 += innovation_um**2 - (variance_um2 - R_um2)
            self._r_count += 1
        self._innovation_um.append(innovation_um)
        self._innovation_var_um2.append(variance_um2)
        outcome = replace(outcome, accepted=True, nis=innovation_um**2 / variance_um2)
        return self._finish_tile(acquisition, outcome, posterior)

    def _finish_tile(
        self,
        acquisition: Acquisition,
        outcome: Outcome,
        posterior: Gaussian,
        *,
        keep_planes: bool = True,
    ) -> Outcome:
        """Record the tile's estimate, image it at the acquired frame nearest it, move on.

        With a stated risk, a measured tile keeps more of its frames where that one is
        too unsure (`lean.kept_planes`; not where `keep_planes` is False: an empty field);
        where its stacks hold too few, the frames it needs are acquired first
        (`lean.planes_stack`, purpose PLANES) and the tile is finished when they come: the
        outcome in between has the final posterior.
        """
        row, col = acquisition.row, acquisition.col
        looked = tuple(z for z in (self._look, self._blurred) if z is not None)
        stacks = (*looked, *self._search.stacks, acquisition.z)
        if self._planes is not None:  # the frames it asked for came: finish with them
            stacks = (*self._planes.stacks, acquisition.z)
            self._planes = None
        frames_um = np.concatenate([z.z_um() for z in stacks])
        self.map.posterior_um[row, col] = posterior.mean_um
        self.map.posterior_sigma_um[row, col] = posterior.sigma_um
        z_used_um = float(frames_um[np.argmin(np.abs(frames_um - posterior.mean_um))])
        self.map.z_used_um[row, col] = z_used_um
        risk = self.map.out_of_focus_risk
        assert risk is not None  # FocusMap.empty made it
        planes_um: tuple[float, ...] = (z_used_um,)
        if not acquisition.measure and acquisition.purpose != Purpose.PLANES:
            risk[row, col] = self._skip_risk
        else:
            dof_um = self.settings.dof_um
            if self.options.risk_out_of_focus and keep_planes:
                planes_um = kept_planes(
                    posterior.mean_um,
                    posterior.sigma_um,
                    frames_um,
                    z_used_um,
                    dof_um,
                    self.options.risk_out_of_focus,
                    self.options.max_kept_planes,
                )
            risk[row, col] = planes_risk(posterior.mean_um, posterior.sigma_um, planes_um, dof_um)
            more = (
                self._planes_to_take(acquisition, posterior, z_used_um, planes_um, risk[row, col])
                if keep_planes
                else None
            )
            if more is not None:
                self._planes = PendingPlanes(more, stacks, posterior, outcome)
                return replace(
                    outcome, posterior_um=posterior.mean_um, posterior_sigma_um=posterior.sigma_um
                )
        self.scanned[row, col] = True
        self._position += 1
        self._prior = None
        self._search.clear()
        self._centre_um = None
        self._look = None
        self._blurred = None
        if self._position == self.grid.n_tiles:
            self._finish()
        return replace(
            outcome,
            posterior_um=posterior.mean_um,
            posterior_sigma_um=posterior.sigma_um,
            planes_um=planes_um if len(planes_um) > 1 else (),
        )
