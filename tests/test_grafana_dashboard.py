"""The Grafana dashboard in deploy/grafana reads metrics the estimator exposes.

Every query of every panel names only metrics (and labels) that a real estimator app
renders at /metrics: a renamed metric would leave a panel silently empty.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from focustrack_estimator.metrics import EstimatorMetrics

DASHBOARD = Path(__file__).parents[1] / "deploy" / "grafana" / "focustrack-facility.json"


def _exposed() -> dict[str, set[str]]:
    """Each metric sample name the estimator renders, with the label names it carries."""
    metrics = EstimatorMetrics(lambda: 1.0, lambda: 1.0, lambda: 1.0, lambda: 0.0)
    metrics.requests.labels("GET", "/v1/slides/{slide_id}/next", "200").inc()
    metrics.latency.labels("/v1/slides/{slide_id}/next").observe(0.001)
    metrics.filter.observe(0.001)
    exposed: dict[str, set[str]] = {}
    for line in metrics.render().splitlines():
        if match := re.match(r"(\w+)(?:\{(.*)\})? ", line):
            labels = {pair.split("=")[0] for pair in (match.group(2) or "").split(",") if pair}
            exposed.setdefault(match.group(1), set()).update(labels)
    return exposed


def test_every_panel_queries_metrics_the_estimator_exposes() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    exposed = _exposed()
    panels = dashboard["panels"]
    assert len({panel["id"] for panel in panels}) == len(panels) >= 6
    for panel in panels:
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            names = re.findall(r"focustrack_estimator_\w+", target["expr"])
            assert names, target["expr"]
            for name in names:
                assert name in exposed, f"{panel['title']}: {name} is not exposed"
                selectors = re.findall(rf"{name}\{{([^}}]*)\}}", target["expr"])
                for selector in selectors:
                    for label in re.findall(r"(\w+)\s*=~?", selector):
                        assert label in exposed[name], f"{name} has no label {label}"
