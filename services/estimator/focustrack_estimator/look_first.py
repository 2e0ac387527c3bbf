"""A tile's first frame alone, then the rest of its stack: an empty tile costs one frame.

With `look_first` (`filter_params.LeanParams`), a tile's first stack is acquired in two parts
where its lowest frame lies within `LOOK_REACH_UM` of its centre (where the focus is
expected: the prediction, or a coarse search's peak): that frame alone (a
look: the focus service says whether anything is in view, `focustrack_focus.look`), then,
where something is, the stack's other frames, which the focus service reads with the
look's frame as one curve (`focustrack_focus.pipeline.LastLooks`). A tile of glass costs
that one frame, wherever it lies; a tile with something in view costs its stack's frames,
as without the look. The look's frame is the stack's lowest, not its centre, so that the
rest is one stack of evenly stepped frames.

The reach keeps the look near focus: the look's statistic was chosen on frames within
1.5 um of focus, where a tile with 0.3% of its area in tissue stands far above glass
(`focustrack_focus.look`); 4 um away, sparse tissue can read as glass. A stack whose
lowest frame lies farther from its centre (a wide or coarse one, where the prediction is
unsure) is taken whole, as without the option. Heights in um.
"""

from __future__ import annotations

from focustrack_core.domain import ZRange

#: The farthest a stack's lowest frame may lie from its centre for it to be looked at
#: first, um (a 3-frame stack of 0.5 um steps: 0.5; 5 frames: 1.0).
LOOK_REACH_UM = 1.0


def first_part(z: ZRange, look: ZRange | None) -> ZRange:
    """What to acquire of a tile's first stack `z`: its lowest frame alone where no look was
    taken on the tile yet and that frame lies within LOOK_REACH_UM of the stack's centre;
    the rest of `z` after a look at that frame; else `z`.

    A stack of fewer than 3 frames is taken whole (its rest would be no curve)."""
    if z.n_frames < 3:
        return z
    if look is None:
        if z.center_um - z.low_um <= LOOK_REACH_UM + 1e-9:
            return ZRange(z.low_um, z.step_um, 1)
        return z
    if look.n_frames == 1 and abs(look.low_um - z.low_um) < 1e-6:
        return ZRange(z.low_um + z.step_um, z.step_um, z.n_frames - 1)
    return z


def with_look(look: ZRange | None, z: ZRange) -> ZRange:
    """The frames a measurement of `z` was read from: `z`, with the look's frame below it
    where `z` is the rest of that look's stack (one step above it and on)."""
    if look is not None and look.n_frames == 1 and abs(z.low_um - z.step_um - look.low_um) < 1e-6:
        return ZRange(look.low_um, z.step_um, z.n_frames + 1)
    return z
