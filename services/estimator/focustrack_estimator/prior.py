"""A slide's prior map uploaded as an .npy file (`PUT /v1/slides/{id}/prior`), checked.

kf-rescan takes the last pass's map as two parameters, `prior_map_um` and
`prior_map_sigma_um`, flat lists row after row. A 200 x 200 map and its sigmas are
about 1.6 MB of JSON, over the 64 KiB a request body may have; as an .npy file they
are 640 kB of float64, under a limit of their own (`max_prior_bytes`). The file holds
a (rows, cols) map of heights, or a (2, rows, cols) stack of the map and its sigmas,
um, float64 or float32: what `np.save` writes of the arrays a map's .npy gives
(`GET /v1/slides/{id}/map?format=npy`, fields `smoothed_um`, `smoothed_sigma_um`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from focustrack_client import models as api
from focustrack_core.stacks import npy_array, npy_header
from focustrack_estimator.errors import SlideError
from focustrack_estimator.maps_out import FILE_MEDIA

if TYPE_CHECKING:
    from focustrack_estimator.strategy import StrategyEntry

#: The media type the route takes: the one the map's .npy is served with.
PRIOR_MEDIA_TYPE = FILE_MEDIA["npy"]

#: Bytes an .npy header may take beyond the data (numpy pads it to 64; a long shape, 128).
NPY_HEADER_BYTES = 4096

#: Where a refused prior is located, as a validation error's `loc` says it.
BODY_LOC = ("body",)


def max_prior_bytes(max_grid_tiles: int) -> int:
    """The largest prior body the service reads: a float64 map and its sigmas for the
    largest grid it serves, and a header."""
    return 2 * 8 * max_grid_tiles + NPY_HEADER_BYTES


@dataclass(frozen=True)
class PriorMap:
    """A checked prior map: heights (rows, cols) um, and their sigmas (None: not given)."""

    map_um: np.ndarray
    sigma_um: np.ndarray | None


def decode_prior(body: bytes, rows: int, cols: int) -> PriorMap:
    """The prior map in the .npy file `body` for a rows x cols grid; a SlideError (422)
    saying what is wrong: not an .npy file, another dtype or shape, a height that is not
    finite or beyond +/- `api.MAX_ABS_UM`, a sigma that is not positive and finite."""
    try:
        shape, dtype = npy_header(body)  # checked before the header's array is made
    except (ValueError, OSError, EOFError) as error:
        raise SlideError(
            f"the body is not an .npy file (np.save writes one): {error}", BODY_LOC
        ) from None
    if dtype.kind != "f" or dtype.itemsize not in (4, 8):
        raise SlideError(f"the prior map must be float64 or float32, got {dtype}", BODY_LOC)
    if shape not in ((rows, cols), (2, rows, cols)):
        raise SlideError(
            f"the prior map of this {rows}x{cols} slide must have shape ({rows}, {cols}) "
            f"(heights), or (2, {rows}, {cols}) (heights and their sigmas), um; got {shape}",
            BODY_LOC,
        )
    try:
        array = npy_array(body)
    except ValueError as error:  # cut short
        raise SlideError(f"the body's .npy file cannot be read: {error}", BODY_LOC) from None
    layers = array.astype(np.float64).reshape(-1, rows, cols)
    map_um = layers[0]
    bounded = np.isfinite(map_um) & (np.abs(map_um) <= api.MAX_ABS_UM)
    _refuse_unless(bounded, map_um, "height", f"within +/-{api.MAX_ABS_UM:g}")
    if len(layers) == 1:
        return PriorMap(map_um, None)
    sigma_um = layers[1]
    positive = np.isfinite(sigma_um) & (sigma_um > 0) & (sigma_um <= api.MAX_ABS_UM)
    _refuse_unless(positive, sigma_um, "sigma", f"positive, at most {api.MAX_ABS_UM:g}")
    return PriorMap(map_um, sigma_um)


def _refuse_unless(ok: np.ndarray, values: np.ndarray, what: str, rule: str) -> None:
    """A SlideError naming the first tile where `ok` is False, and how many there are."""
    if ok.all():
        return
    row, col = (int(i) for i in np.argwhere(~ok)[0])
    raise SlideError(
        f"every {what} of the prior map must be finite and {rule} um: tile ({row}, {col}) "
        f"has {float(values[row, col])} ({int((~ok).sum())} tiles in all)",
        BODY_LOC,
    )


def with_prior(config: api.SlideCreate, prior: PriorMap) -> api.SlideCreate:
    """`config` with `prior` as its map parameters: the heights, and the sigmas if given
    (else the configuration's own stay: one for every tile, or the strategy's default)."""
    params = {**config.params, api.PRIOR_MAP_PARAM: prior.map_um.ravel().tolist()}
    if prior.sigma_um is not None:
        params[api.PRIOR_SIGMA_PARAM] = prior.sigma_um.ravel().tolist()
    return config.model_copy(update={"params": params})


def takes_prior(entry: StrategyEntry[Any]) -> bool:
    """Whether a strategy takes a prior map (its parameters have the map's)."""
    fields = entry.params.model_fields
    return api.PRIOR_MAP_PARAM in fields and api.PRIOR_SIGMA_PARAM in fields
