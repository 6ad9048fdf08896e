"""Prometheus metrics of the federates (base units, ``cosim_`` prefix, ``_total`` counters).

A federate serves them over HTTP when ``COSIM5G_METRICS_PORT`` is set (the docker runtime sets it
for every container when ``COSIM5G_FEDERATE_METRICS_PORT`` is given); otherwise they are only
collected in-process.
"""

from __future__ import annotations

import logging
from bisect import bisect_left
from collections import Counter as Tally
from typing import Any

from prometheus_client import Counter, Gauge, Histogram, start_http_server

from fabric.settings import env_name, settings

log = logging.getLogger(__name__)
# The port a federate serves its metrics on: a runtime whose federates share a host never passes
# it on (the docker runtime gives each container its own).
PORT_ENV = env_name("metrics_port")

_LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)

JOB_DURATION = Histogram("cosim_compute_job_duration_seconds", "Emulated duration of a compute job",
                         ["node", "kind"], buckets=_LATENCY_BUCKETS)
JOB_QUEUE = Histogram("cosim_compute_job_queue_seconds", "Queueing delay of a compute job",
                      ["node", "kind"], buckets=_LATENCY_BUCKETS)
JOB_CPU = Counter("cosim_compute_job_cpu_seconds_total", "Host CPU time consumed by jobs", ["node", "kind"])
JOB_THROTTLED = Counter("cosim_compute_job_throttled_seconds_total",
                        "CPU time the node's cgroup quota throttled during jobs", ["node", "kind"])
WINDOWS = Counter("cosim_federate_windows_total", "Time windows processed", ["federate"])
EVENTS = Counter("cosim_federate_events_total", "Events (inputs and internal) processed", ["federate"])
MESSAGES_SENT = Counter("cosim_federate_messages_sent_total", "Data messages sent", ["federate", "plane"])
PACKET_LATENCY = Histogram("cosim_netsim_packet_latency_seconds", "IP packet latency, enqueue to delivery",
                           ["direction"], buckets=_LATENCY_BUCKETS)
PACKETS = Counter("cosim_netsim_packets_total", "IP packets by fate", ["direction", "outcome"])
PACKET_BYTES = Counter("cosim_netsim_delivered_bytes_total", "IP bytes delivered", ["direction"])
# Rates over simulated time (a run is rarely real time, so wall-clock rates of the counters above
# say how fast the simulation goes, these what the cell carries).
THROUGHPUT = Gauge("cosim_netsim_throughput_bits_per_second",
                   "IP bits delivered over the last simulated second", ["direction"])
PRB_UTILISATION = Gauge("cosim_netsim_prb_utilisation",
                        "Share of the PRBs of the last simulated second that carried data", ["direction"])
TASKS = Counter("cosim_physics_tasks_total", "Pick-and-place tasks ended, by outcome", ["outcome"])
LOOP_PDP = Gauge("cosim_loop_pdp", "Packet delivery probability the co-design policy set for a loop", ["loop"])
# Per Edge (its name in the run's edges.json): a series exists only where an Edge runs.
QUEUEING_DELAY = Gauge("cosim_edge_queueing_delay_seconds",
                       "Smoothed queueing delay of the frames the Edge receives (delay above each loop's smallest)",
                       ["edge"])
PDP_FILL = Gauge("cosim_edge_pdp_fill", "PDP every co-design loop may use while the radio cell has headroom", ["edge"])
PDP_CAP = Gauge("cosim_edge_pdp_cap", "PDP no co-design loop may exceed (the congestion guard)", ["edge"])
LOOPS_SERVED = Gauge("cosim_edge_loops_served", "Share of the Edge's loops the congestion guard serves (the others shed)",
                     ["edge"])


def observe_many(histogram: Any, value: float, count: int) -> None:
    """``count`` observations of ``value`` (in the histogram's unit: seconds for the latencies
    here) in a Histogram child, which has no bulk observe: its sum and the bucket ``observe``
    would pick (the first bound >= value), each updated once."""
    histogram._sum.inc(value * count)
    histogram._buckets[bisect_left(histogram._upper_bounds, value)].inc(count)


def observe_all(histogram: Any, values: list[float]) -> None:
    """An observation of each of ``values`` (in the histogram's unit) in a Histogram child: the
    same counts and sum as ``observe`` one by one, each bucket and the sum updated once (a lock
    each, not a lock each a value)."""
    if not values:
        return
    bounds = histogram._upper_bounds
    histogram._sum.inc(sum(values))
    for bucket, n in Tally(bisect_left(bounds, v) for v in values).items():
        histogram._buckets[bucket].inc(n)


def serve_from_env() -> int | None:
    """Start the HTTP metrics endpoint on ``COSIM5G_METRICS_PORT`` if it is set; returns that
    port, or None."""
    port = settings().metrics_port
    if port is None:
        return None
    try:
        start_http_server(port)
    except OSError as exc:  # metrics are for watching: a taken port must not end the run
        log.warning("metrics not served: cannot listen on %s=%d: %s", PORT_ENV, port, exc)
        return None
    return port
