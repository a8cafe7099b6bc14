"""deploy/grafana/dncq-dashboard.json: valid JSON for Grafana's import, on a Prometheus data
source chosen at import, and every query over metrics that /metrics really exposes."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

DASHBOARD = Path(__file__).resolve().parents[2] / "deploy" / "grafana" / "dncq-dashboard.json"
METRIC_NAME = re.compile(r"\b((?:dncq|process|python)_[A-Za-z0-9_]+)")


def dashboard() -> dict[str, Any]:
    data: dict[str, Any] = json.loads(DASHBOARD.read_text())
    return data


def queries() -> list[str]:
    return [target["expr"] for panel in dashboard()["panels"]
            for target in panel.get("targets", [])]


def test_the_dashboard_asks_for_a_prometheus_data_source_and_every_panel_uses_it():
    [variable] = [v for v in dashboard()["templating"]["list"] if v["type"] == "datasource"]
    assert variable["query"] == "prometheus"
    for panel in dashboard()["panels"]:
        if panel["type"] != "row":
            assert panel["datasource"] == {"type": "prometheus", "uid": f"${{{variable['name']}}}"}


SERIES = {"counter": ("_total",), "histogram": ("_bucket", "_sum", "_count"),
          "summary": ("", "_sum", "_count"), "gauge": ("",), "info": ("_info",)}


def exposed_series(exposition: str) -> set[str]:
    """The series names an exposition declares: its samples', and its families' by their
    type (a family with no sample yet, such as the machines of an empty registry, counts)."""
    names = set()
    for family in text_string_to_metric_families(exposition):
        names.update(sample.name for sample in family.samples)
        names.update(family.name + suffix for suffix in SERIES.get(family.type, ("",)))
    return names


def test_every_query_names_only_metrics_that_metrics_exposes(client):
    exposed = exposed_series(client.get("/metrics").text)
    for expr in queries():
        names = set(METRIC_NAME.findall(expr))
        assert names, expr
        assert names <= exposed, f"{expr}: {names - exposed}"


def test_the_dashboard_shows_each_part_of_the_fleet():
    asked = " ".join(queries())
    for name in ("dncq_jobs_finished_total", "dncq_targets_finished_total",
                 "dncq_target_duration_seconds_bucket", "dncq_bytes_moved_total",
                 "dncq_targets_pending", "dncq_target_retries_total", "dncq_backups_total",
                 "dncq_dnc_lines_sent_total", "dncq_machines"):
        assert name in asked, name
