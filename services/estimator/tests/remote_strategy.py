"""A slide served by an estimator, driven as a local `Strategy` (for the end-to-end test).

`RemoteStrategy` turns a slide on an estimator service back into the two calls
every strategy answers, so anything that drives a strategy (`replay.replay`, the
benchmarks' driver) drives a served slide the same way; the end-to-end test
(test_estimator_e2e.py) uses that to check that the service reproduces the benchmark
exactly. A client of the service's own API, so a test helper, not part of the service.
"""

from __future__ import annotations

from typing import Any

from focustrack_client import EstimatorClient
from focustrack_core.domain import Acquisition, FocusMap, Measurement, Outcome, SlideSettings
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.rest import to_api, to_domain
from focustrack_estimator.strategy import Strategy


class RemoteStrategy(Strategy):
    """A slide on an estimator service, driven through the Strategy interface."""

    def __init__(
        self, client: EstimatorClient, slide_id: str, settings: SlideSettings, name: str
    ) -> None:
        super().__init__(settings)
        self.client, self.slide_id, self.name = client, slide_id, name

    @classmethod
    def create(
        cls,
        client: EstimatorClient,
        strategy: str,
        settings: SlideSettings,
        params: dict[str, Any] | None = None,
    ) -> RemoteStrategy:
        """A new slide on the service, scanned with `strategy`."""
        slide = client.create_slide(to_api.slide_create(strategy, settings, params))
        return cls(client, slide.id, settings, strategy)

    def _plan(self) -> Acquisition | None:
        return to_domain.acquisition(self.client.next(self.slide_id))

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        body = to_api.measurement_in(acquisition, measurement)
        return to_domain.outcome(self.client.measure(self.slide_id, body))

    def focus_map(self) -> FocusMap:
        return focus_map_of_npy(self.client.focus_map_file(self.slide_id, "npy"))
