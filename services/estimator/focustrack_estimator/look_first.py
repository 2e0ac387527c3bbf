"""A tile's first frame alone, then the rest of its stack: an empty tile costs one frame.

With `look_first` (`filter_params.LeanParams`), a tile's first measured acquisition of two
frames or more is preceded by a look: one frame, which the focus service answers empty or
not (`focustrack_focus.look`: a tile's stain against its pixel noise, which tells glass from
tissue at any defocus within a slide's range, coverslip dust or not). A tile of glass costs
that one frame, wherever it lies and whether its height is known or not (a slide's first
tile); where something is in view, the stack follows:

- where the stack's lowest frame lies within `LOOK_REACH_UM` of its centre (a short stack,
  a pair, a 5-frame stack: the height is known), the look is that frame and the rest of the
  stack follows, which the focus service reads with the look's frame as one curve
  (`focustrack_focus.pipeline.LastLooks`): the tile costs its stack's frames, no more;
- otherwise (a wide or coarse stack: the height is unsure), the look is one frame at the
  stack's centre (the prediction) and the whole stack follows: one frame more on such a
  tile with tissue, the price of a tile of glass at one frame rather than the stack.

The look's frame is a short stack's lowest, not its centre, so that the rest is one stack of
evenly stepped frames. Heights in um.
"""

from __future__ import annotations

from focustrack_core.domain import ZRange

#: The farthest a stack's lowest frame may lie from its centre for the look to be that frame
#: and the rest of the stack to follow, um (a 3-frame stack of 0.5 um steps: 0.5; 5 frames:
#: 1.0); a stack wider than that is looked at its centre, then taken whole.
LOOK_REACH_UM = 1.0


def first_part(z: ZRange, look: ZRange | None) -> ZRange:
    """What to acquire of a tile's first stack `z` (two frames or more; one is taken as is):
    with no look taken on the tile yet, its lowest frame alone where that lies within
    LOOK_REACH_UM of its centre, else one frame at its centre; the rest of `z` after a look
    at its lowest frame; else `z` (after a look at its centre)."""
    if z.n_frames < 2:
        return z
    if look is None:
        if z.center_um - z.low_um <= LOOK_REACH_UM + 1e-9:
            return ZRange(z.low_um, z.step_um, 1)
        return ZRange.centred(z.center_um, 1, z.step_um)
    if look.n_frames == 1 and abs(look.low_um - z.low_um) < 1e-6:
        return ZRange(z.low_um + z.step_um, z.step_um, z.n_frames - 1)
    return z


def with_look(look: ZRange | None, z: ZRange) -> ZRange:
    """The frames a measurement of `z` was read from: `z`, with the look's frame below it
    where `z` is the rest of that look's stack (one step above it and on)."""
    if look is not None and look.n_frames == 1 and abs(z.low_um - z.step_um - look.low_um) < 1e-6:
        return ZRange(look.low_um, z.step_um, z.n_frames + 1)
    return z
