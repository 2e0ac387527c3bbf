"""The estimator's settings: every option of `focustrack serve estimator`, each default once.

Flags, ``FOCUSTRACK_ESTIMATOR_<OPTION>`` variables and a ``--settings`` file all
read this model (`focustrack_core.settings`); the app, the grid limits and the
cost budget take their values from it.
"""

from __future__ import annotations

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from focustrack_core.tracing import TracingSettings
from focustrack_estimator.event_store import STORE_TIMEOUT_S

#: The smallest request-body limit: a slide's configuration with its fields spelt out
#: (about 400 bytes) under it with room; a smaller one would refuse every slide.
MIN_BODY_BYTES = 1024


class EstimatorSettings(TracingSettings):
    """How the estimator service runs: where, on which store, with which limits, and where
    its traces go."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_ESTIMATOR_")

    host: str = Field("127.0.0.1", description="address to bind")
    port: int = Field(8100, ge=0, le=65535, description="TCP port")
    store: str = Field(
        "estimator.sqlite",
        min_length=1,
        description="SQLite file holding every slide and its log (created if missing), "
        "its sqlite:///PATH URL, or a PostgreSQL database shared by replicas "
        "(postgresql://USER:PASS@HOST:PORT/DB; the tables are created in it)",
    )
    store_timeout_s: float = Field(
        STORE_TIMEOUT_S,
        gt=0,
        description="seconds a request waits for a connection to a PostgreSQL store (then: 503)",
    )
    token: str | None = Field(None, description="require this bearer token on /v1 (unset: no auth)")
    insecure: bool = Field(
        False, description="serve without a token on a non-loopback address (refused otherwise)"
    )
    max_body_bytes: int = Field(
        64 * 1024,
        ge=MIN_BODY_BYTES,
        description="largest request body accepted, at least 1 KiB, a slide's configuration "
        "with its fields spelt out (a prior map's .npy: its own limit, the largest grid's map "
        "and sigmas)",
    )
    max_grid_side: int = Field(
        500, ge=1, description="most tiles per side a slide's grid may have (larger: 422)"
    )
    max_grid_tiles: int = Field(
        250_000, ge=1, description="most tiles a slide's grid may have (larger: 422)"
    )
    snapshot_every: int = Field(
        200,
        ge=1,
        description="measurements between snapshots of a slide's state (a restart replays fewer)",
    )
    body_timeout_s: float = Field(
        30.0, gt=0, description="seconds a request body may take to arrive (slower: 408)"
    )
    # The defaults admit kf-2d on a 200x200 grid (about 220 MiB, 2.5 ms per tile).
    max_slide_bytes: int = Field(
        512 * 2**20,
        ge=1,
        description="largest projected memory of one slide, bytes (more: 422 at creation)",
    )
    max_tile_seconds: float = Field(
        0.1,
        gt=0,
        description="largest projected computation per tile of a slide, seconds (more: 422)",
    )
    max_live_slides: int = Field(
        100,
        ge=1,
        description="slides kept in memory; the least recently used beyond are evicted "
        "(reloaded from the store on their next request)",
    )
    max_live_bytes: int = Field(
        768 * 2**20,
        ge=1,
        description="projected bytes the slides in memory may hold together (beyond: evicted)",
    )
    strategies_from: str | None = Field(
        None,
        description="serve the strategies of MODULE's CATALOGUE instead of the estimator's own "
        "(opt-in: focustrack.bench.strategies adds gp-oracle, the benchmarks' floor)",
    )
    access_log: bool = Field(False, description="log every request")

    @field_validator("token", "strategies_from")
    @classmethod
    def _empty_is_unset(cls, value: str | None) -> str | None:
        """An empty token is no token (`--token ''`), as an empty module is none."""
        return value or None

    @field_validator("token")
    @classmethod
    def _sendable(cls, token: str | None) -> str | None:
        """A token a client can send: in an HTTP header a token of blanks, or with a blank
        or a control character at an end or a line break inside, cannot be sent whole."""
        if token is not None and (
            token != token.strip() or not token.isprintable() or not token.isascii()
        ):
            raise ValueError(
                "must be printable ASCII without blanks at either end (no client could "
                "send it in the Authorization header)"
            )
        return token
