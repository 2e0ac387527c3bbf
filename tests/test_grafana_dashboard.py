"""The Grafana dashboard in deploy/grafana reads metrics the services expose.

Every query of every panel names only metrics (and labels) that the estimator, a scan and an
instrument render at /metrics: a renamed metric would leave a panel silently empty.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from focustrack_core.http_metrics import RegistryMetrics
from focustrack_estimator.metrics import EstimatorMetrics
from focustrack_instrument_sim.metrics import InstrumentMetrics
from focustrack_scheduler.telemetry import ScanMetrics

#: Labels Prometheus gives every sample it scrapes (and a histogram's bucket bound).
PROMETHEUS_LABELS = {"instance", "job", "le"}

DASHBOARD = Path(__file__).parents[1] / "deploy" / "grafana" / "focustrack-facility.json"


def _exposed() -> dict[str, set[str]]:
    """Each metric sample name the services render, with the label names it carries."""
    estimator = EstimatorMetrics(lambda: 1.0, lambda: 1.0, lambda: 1.0, lambda: 0.0)
    estimator.requests.labels("GET", "/v1/slides/{slide_id}/next", "200").inc()
    estimator.latency.labels("/v1/slides/{slide_id}/next").observe(0.001)
    estimator.filter.observe(0.001)
    scan = ScanMetrics()
    scan.step_latency.labels("Acquire").observe(0.1)
    scan.tile_latency.observe(1.0)
    instrument = InstrumentMetrics(lambda: 0.0)
    instrument.errors.labels("ERROR_CODE_Z_OUT_OF_RANGE").inc()
    instrument.latency.observe(0.1)
    exposed: dict[str, set[str]] = {}
    services: tuple[RegistryMetrics, ...] = (estimator, scan, instrument)
    for line in "\n".join(service.render() for service in services).splitlines():
        if match := re.match(r"(\w+)(?:\{(.*)\})? ", line):
            labels = {pair.split("=")[0] for pair in (match.group(2) or "").split(",") if pair}
            exposed.setdefault(match.group(1), set()).update(labels)
    return exposed


def test_every_panel_queries_metrics_the_services_expose() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    exposed = _exposed()
    panels = dashboard["panels"]
    assert len({panel["id"] for panel in panels}) == len(panels) >= 16
    for panel in panels:
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            names = re.findall(r"focustrack_(?:estimator|scan|instrument)_\w+", target["expr"])
            assert names, target["expr"]
            for name in names:
                assert name in exposed, f"{panel['title']}: {name} is not exposed"
                selectors = re.findall(rf"{name}\{{([^}}]*)\}}", target["expr"])
                for selector in selectors:
                    for label in re.findall(r"(\w+)\s*=~?", selector):
                        assert label in exposed[name], f"{name} has no label {label}"
            # a sum by a label: some metric of the query has it (or Prometheus adds it)
            for grouping in re.findall(r"by \(([^)]*)\)", target["expr"]):
                for label in re.findall(r"\w+", grouping):
                    carried = set().union(*(exposed[name] for name in names))
                    assert label in carried | PROMETHEUS_LABELS, f"no metric of {names} has {label}"
