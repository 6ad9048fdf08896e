"""``cosim5g netsim``: the NR cell alone, loaded by N uplink cameras, no other federate.

Each camera sends one frame of ``rate_mbps / frame_rate`` megabits every 1/frame_rate s, cut into
1500-byte IP packets that enter the UE buffer at the next slot boundary after capture. Cameras
are not synchronised: camera i starts at a random phase (seeded). The run reports offered load,
delivered uplink IP throughput, IP packet latency (enqueue to delivery) and losses by cause.

Reference layout (documented in docs/netsim.md): the 120 x 60 x 10 m InF-SL hall, gNB at the
centre (60, 30, 1.5) m, camera i at (5 + 110 h2(i+1), 5 + 50 h3(i+1), 1.5) m where h2, h3 are the
base-2 and base-3 radical inverses (a Halton sequence). Every prefix of the sequence covers the
hall evenly and camera i sits at the same place whatever N is, so runs with different N share
their first cameras' channels.
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import sys
import time
from collections import Counter
from itertools import repeat
from operator import attrgetter
from typing import Any

import numpy as np
from pydantic import ValidationError

from fabric.heap import simulation_heap
from fabric.seeding import rng as named_rng
from netsim.nr.layout import InfLayout, drop_ues
from netsim.nr.multicell import MultiCell
from netsim.nr.radio_cell import NrCell
from netsim.radio_cell import (
    LOSS_BUFFER,
    LOSS_CHANNEL,
    LOSS_DELAY_BUDGET,
    FlowQos,
    Packet,
    RadioCell,
)
from scenario.lattice import LATTICE_COLUMNS, LATTICE_ROWS
from scenario.nr import NrConfig

GNB_HEIGHT_M = 1.5
UE_HEIGHT_M = 1.5
HALL_MARGIN_M = 5.0
PACKET_BYTES = 1500


def radical_inverse(i: int, base: int) -> float:
    """Van der Corput radical inverse of ``i`` in ``base`` (in [0, 1))."""
    f, r = 1.0, 0.0
    while i > 0:
        f /= base
        r += f * (i % base)
        i //= base
    return r


def camera_layout(n_ues: int, config: NrConfig | None = None
                  ) -> tuple[tuple[float, float, float], dict[str, tuple[float, float, float]]]:
    """gNB position and camera positions ``camera-<i>`` of the reference layout."""
    cfg = config or NrConfig()
    length, width = cfg.hall_length_m, cfg.hall_width_m
    gnb = (length / 2, width / 2, GNB_HEIGHT_M)
    ues = {
        f"camera-{i}": (
            round(HALL_MARGIN_M + (length - 2 * HALL_MARGIN_M) * radical_inverse(i + 1, 2), 3),
            round(HALL_MARGIN_M + (width - 2 * HALL_MARGIN_M) * radical_inverse(i + 1, 3), 3),
            UE_HEIGHT_M,
        )
        for i in range(n_ues)
    }
    return gnb, ues


def run_uplink_cameras(n_ues: int, rate_mbps: float, duration_s: float, *,
                       frame_rate: float = 30.0, seed: int = 0,
                       config: NrConfig | None = None, warmup_s: float | None = None,
                       delay_budget_us: int | None = None,
                       packet_bytes: int = PACKET_BYTES) -> dict[str, Any]:
    """Run the camera scenario and return its KPIs (the ``--json`` record).

    Throughput counts IP bytes delivered after the warm-up; latency and losses count packets
    enqueued after the warm-up (packets still queued at the end are reported as in flight).
    """
    cfg = config or NrConfig()
    gnb, ues = camera_layout(n_ues, cfg)
    cell = NrCell(cfg, gnb, ues, seed)
    result = _drive_cameras(cell, list(ues), cfg, rate_mbps, duration_s, frame_rate, seed,
                            warmup_s, delay_budget_us, packet_bytes)
    ul = cell.stats()["ul"]
    hist = np.array(ul["mcs_histogram"], dtype=float)
    result["mcs_mean_ul"] = (float((hist * np.arange(hist.size)).sum() / hist.sum())
                             if hist.sum() else None)
    return result


def hall_layout(n_gnbs: int, ues_per_gnb: int, seed: int, config: NrConfig | None = None,
                reuse: int = 1, sub_scenario: str = "SL"
                ) -> tuple[InfLayout, dict[str, tuple[float, float, float]]]:
    """``n_gnbs`` gNBs of the InF lattice of the hall of ``config`` (a subset, docs/netsim.md)
    on ``reuse``, and ``ues_per_gnb`` cameras ``camera-<i>`` dropped uniformly over the lattice
    square of each gNB (pitch length/6 x width/3 around it, at least 1 m from it), UE height
    1.5 m; drawn from the stream ``standalone/drop/<gnb id>``. Association (strongest RSRP)
    keeps most of them with that gNB."""
    cfg = config or NrConfig()
    layout = InfLayout.lattice(sub_scenario, cfg.hall_length_m, cfg.hall_width_m,
                               cfg.hall_height_m, n_gnbs, reuse)
    px, py = cfg.hall_length_m / LATTICE_COLUMNS, cfg.hall_width_m / LATTICE_ROWS
    ues: dict[str, tuple[float, float, float]] = {}
    for gnb_id, (x, y, _) in zip(layout.gnb_ids, layout.gnb_positions_m, strict=True):
        drop = drop_ues(ues_per_gnb, px, py, named_rng(seed, f"standalone/drop/{gnb_id}"),
                        np.array([[px / 2, py / 2, 0.0]]), UE_HEIGHT_M)
        for dx, dy, z in drop:
            ues[f"camera-{len(ues)}"] = (round(float(x - px / 2 + dx), 3),
                                         round(float(y - py / 2 + dy), 3), float(z))
    return layout, ues


def run_hall_cameras(n_gnbs: int, ues_per_gnb: int, rate_mbps: float, duration_s: float, *,
                     reuse: int = 1, sub_scenario: str = "SL", frame_rate: float = 30.0,
                     seed: int = 0, config: NrConfig | None = None,
                     warmup_s: float | None = None) -> dict[str, Any]:
    """The camera scenario on several cells (``netsim.nr.multicell.MultiCell``): the gNBs and
    cameras of ``hall_layout``, each camera sending as in ``run_uplink_cameras``; its KPIs,
    with the hall's PRB utilisation and UL BLER, the UL SINR percentiles and per gNB the UEs
    served and the UL throughput."""
    cfg = config or NrConfig()
    layout, ues = hall_layout(n_gnbs, ues_per_gnb, seed, cfg, reuse, sub_scenario)
    cell = MultiCell(cfg, layout, ues, seed)
    result = _drive_cameras(cell, list(ues), cfg, rate_mbps, duration_s, frame_rate, seed,
                            warmup_s, None, PACKET_BYTES)
    st = cell.stats()
    result.update(
        gnbs=n_gnbs, reuse=reuse, n_prb=cell.n_cell_prb,
        ul_sinr_db={q: st["ul"][f"sinr_db_{q}"] for q in ("p5", "p50", "p95")},
        ues_per_gnb={f"gnb{g}": st[f"gnb{g}"]["ue_count"] for g in cell.cell_gnb},
        gnb_ul_throughput_mbps={
            f"gnb{g}": st[f"gnb{g}"]["ul"]["delivered_bytes"] * 8 / result["duration_s"] / 1e6
            for g in cell.cell_gnb})
    return result


def _drive_cameras(cell: RadioCell, ue_ids: list[str], cfg: NrConfig, rate_mbps: float,
                   duration_s: float, frame_rate: float, seed: int, warmup_s: float | None,
                   delay_budget_us: int | None, packet_bytes: int) -> dict[str, Any]:
    """Drive ``cell`` with one camera per UE of ``ue_ids`` for ``duration_s``; the KPIs of
    ``run_uplink_cameras`` but the MCS."""
    n_ues = len(ue_ids)
    slot_us = cell.slot_us
    duration_us = int(round(duration_s * 1e6))
    n_slots = duration_us // slot_us
    end_us = n_slots * slot_us
    warmup_us = int(round((min(0.5, 0.1 * duration_s) if warmup_s is None else warmup_s) * 1e6))
    if end_us - warmup_us < slot_us:  # the rates are over the slots after the warm-up
        raise ValueError(f"duration_s = {duration_s:g} s leaves no whole slot ({slot_us} us) after the "
                         f"warm-up ({warmup_us / 1e6:g} s): give at least the warm-up plus one slot")
    frame_bytes = max(1, int(round(rate_mbps * 1e6 / 8 / frame_rate)))
    sizes = [packet_bytes] * (frame_bytes // packet_bytes)
    if frame_bytes % packet_bytes:
        sizes.append(frame_bytes % packet_bytes)
    n_sizes = len(sizes)
    period_us = 1e6 / frame_rate
    if delay_budget_us is not None:
        for ue in ue_ids:
            cell.set_flow_qos(ue, FlowQos(delay_budget_us=delay_budget_us))

    # (enqueue slot boundary, camera, frame index): frames enter at the boundary after capture.
    frames: list[tuple[int, int, int, int]] = []
    for i in range(n_ues):
        phase_us = float(named_rng(seed, f"standalone/camera-{i}/phase").uniform(0, period_us))
        capture = int(phase_us)
        frames.append((-(-capture // slot_us) * slot_us, i, 0, int(phase_us)))
    heapq.heapify(frames)

    packet_id = 0
    latencies_us: list[int] = []
    delivered_bytes = 0
    lost = {LOSS_BUFFER: 0, LOSS_DELAY_BUDGET: 0, LOSS_CHANNEL: 0}
    cell_s = 0.0  # inside enqueue (with packet creation) and run_slot
    run_slot_s = 0.0  # inside run_slot only
    refused_causes: Counter[str | None] = Counter()
    cause_of = attrgetter("cause")
    wall0 = time.perf_counter()
    for s in range(n_slots):
        t = s * slot_us
        c0 = time.perf_counter()
        while frames and frames[0][0] <= t:
            enq, i, k, phase = heapq.heappop(frames)
            ue = ue_ids[i]
            # The frame's packets, ids packet_id + 1 on (map: no bytecode per packet).
            refused = cell.enqueue_many(list(map(
                Packet, range(packet_id + 1, packet_id + n_sizes + 1), repeat(ue, n_sizes),
                repeat(ue, n_sizes), repeat("ul", n_sizes), sizes, repeat(enq, n_sizes))))
            if refused and enq >= warmup_us:
                # Those refused are the frame's (enqueued at enq): counted by cause in C.
                refused_causes.update(map(cause_of, refused))
            packet_id += n_sizes
            capture = phase + int((k + 1) * period_us)
            heapq.heappush(frames, (-(-capture // slot_us) * slot_us, i, k + 1, phase))
        c1 = time.perf_counter()
        outcomes = cell.run_slot(t)
        c2 = time.perf_counter()
        cell_s += c2 - c0
        run_slot_s += c2 - c1
        for o in outcomes:
            p = o.packet
            if o.deliver_us is not None:
                if o.deliver_us > warmup_us:
                    delivered_bytes += p.size_bytes
                if p.enqueue_us >= warmup_us:
                    latencies_us.append(o.deliver_us - p.enqueue_us)
            elif p.enqueue_us >= warmup_us:
                lost[o.cause or LOSS_CHANNEL] += 1
    wall_s = time.perf_counter() - wall0
    for cause, count in refused_causes.items():
        lost[cause or LOSS_CHANNEL] += count
    # Packets enqueued after the warm-up, whatever became of them.
    sent_in_window = sum(
        len(sizes) * _frames_between(phase, period_us, slot_us, warmup_us, end_us)
        for phase in (f[3] for f in frames))
    lat = np.array(latencies_us, dtype=float) / 1000.0
    ul = cell.stats()["ul"]
    window_s = (end_us - warmup_us) / 1e6
    return {
        "ues": n_ues,
        "rate_mbps": rate_mbps,
        "frame_rate": frame_rate,
        "frame_bytes": frame_bytes,
        "duration_s": end_us / 1e6,
        "warmup_s": warmup_us / 1e6,
        "seed": seed,
        "n_prb": cfg.n_prb,
        "ul_data_symbols": cfg.ul_data_symbols,
        "dl_data_symbols": cfg.dl_data_symbols,
        "offered_mbps": n_ues * frame_bytes * 8 * frame_rate / 1e6,
        "ul_throughput_mbps": delivered_bytes * 8 / window_s / 1e6,
        "ip_latency_ms": {
            "p50": float(np.percentile(lat, 50)) if lat.size else None,
            "p90": float(np.percentile(lat, 90)) if lat.size else None,
            "p99": float(np.percentile(lat, 99)) if lat.size else None,
            "mean": float(lat.mean()) if lat.size else None,
            "max": float(lat.max()) if lat.size else None,
        },
        "sent_packets": sent_in_window,
        "delivered_packets": len(latencies_us),
        "lost_packets": lost,
        "in_flight_packets": max(0, sent_in_window - len(latencies_us) - sum(lost.values())),
        "prb_utilisation_ul": ul["prb_utilisation"],
        "bler_ul": ul["bler_first_transmission"],
        "harq_retransmissions_ul": ul["harq_retransmissions"],
        "slots": n_slots,
        "wall_s": wall_s,
        "slots_per_second": n_slots / wall_s if wall_s > 0 else None,
        "cell_slots_per_second": n_slots / cell_s if cell_s > 0 else None,
        "run_slot_per_second": n_slots / run_slot_s if run_slot_s > 0 else None,
    }


def _frames_between(phase_us: int, period_us: float, slot_us: int, start_us: int,
                    end_us: int) -> int:
    """Frames of a camera whose packets enter the buffer in [start_us, end_us)."""
    count = 0
    k = max(0, int((start_us - phase_us) // period_us) - 1)
    while True:
        enq = -(-(phase_us + int(k * period_us)) // slot_us) * slot_us
        if enq >= end_us:
            return count
        if enq >= start_us:
            count += 1
        k += 1


def _positive(kind: type, name: str) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{name} must be a {kind.__name__}, got {text!r}") from None
        if not value > 0 or (isinstance(value, float) and not math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"{name} must be > 0, got {text!r}")
        return value
    return parse


def _parse_overrides(parser: argparse.ArgumentParser, items: list[str]) -> NrConfig:
    values: dict[str, Any] = {}
    for item in items:
        field, sep, raw = item.partition("=")
        if not sep or not field:
            parser.error(f"--set expects FIELD=VALUE, got {item!r}")
        if field not in NrConfig.model_fields:
            parser.error(f"--set {field}: not an NrConfig field (see docs/netsim.md)")
        try:
            values[field] = json.loads(raw)
        except json.JSONDecodeError:
            values[field] = raw
    try:
        return NrConfig(**values)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(x) for x in first["loc"]) or "config"
        parser.error(f"--set {where}: {first['msg']}")
    raise AssertionError("unreachable")  # parser.error exits


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cosim5g netsim``; returns the exit code (2 on bad arguments)."""
    parser = argparse.ArgumentParser(
        prog="cosim5g netsim",
        description="Run the NR cell alone with N uplink cameras and report throughput, "
        "latency and losses.")
    parser.add_argument("--ues", type=_positive(int, "--ues"), required=True,
                        help="number of uplink cameras (UEs)")
    parser.add_argument("--rate-mbps", type=_positive(float, "--rate-mbps"), required=True,
                        help="camera bit rate per UE, Mbit/s")
    parser.add_argument("--duration-s", type=_positive(float, "--duration-s"), required=True,
                        help="simulated duration, s")
    parser.add_argument("--frame-rate", type=_positive(float, "--frame-rate"), default=30.0,
                        help="frames per second per camera (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="root seed (default 0)")
    parser.add_argument("--warmup-s", type=float, default=None,
                        help="excluded start-up time, s (default min(0.5, 10%% of duration))")
    parser.add_argument("--delay-budget-ms", type=_positive(float, "--delay-budget-ms"),
                        default=None, help="packet delay budget of every camera flow")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="FIELD=VALUE", help="override an NrConfig field (repeatable)")
    parser.add_argument("--json", action="store_true",
                        help="print the result as one JSON object on the last line")
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--"]:  # a wrapper CLI passing its remainder verbatim (cosim5g netsim -- ...)
        argv = argv[1:]
    args = parser.parse_args(argv)
    if args.warmup_s is not None and not 0 <= args.warmup_s < args.duration_s:
        parser.error(f"--warmup-s must be in [0, --duration-s), got {args.warmup_s}")
    config = _parse_overrides(parser, args.overrides)
    budget = None if args.delay_budget_ms is None else int(round(args.delay_budget_ms * 1000))
    with simulation_heap():
        try:
            result = run_uplink_cameras(
                args.ues, args.rate_mbps, args.duration_s, frame_rate=args.frame_rate, seed=args.seed,
                config=config, warmup_s=args.warmup_s, delay_budget_us=budget)
        except ValueError as exc:
            parser.error(f"--duration-s: {exc}")
    lat = result["ip_latency_ms"]
    print(f"{result['ues']} cameras x {result['rate_mbps']:g} Mbps, "
          f"{result['duration_s']:g} s simulated, seed {result['seed']}, "
          f"{result['n_prb']} PRB, {result['ul_data_symbols']} PUSCH symbols")
    print(f"offered {result['offered_mbps']:.1f} Mbps, delivered "
          f"{result['ul_throughput_mbps']:.1f} Mbps, PRB use {result['prb_utilisation_ul']:.1%}, "
          f"BLER {result['bler_ul']:.3f}")
    if lat["p50"] is not None:
        print(f"IP latency p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms")
    print(f"lost packets {result['lost_packets']}, {result['slots_per_second']:.0f} slots/s")
    if args.json:
        print(json.dumps(result))
    return 0
