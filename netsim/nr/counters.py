"""The NR cell's counters: what each transmission, delivery and loss adds, and the ``stats()``
report built from them (docs/netsim.md, "Counters")."""

from __future__ import annotations

from typing import Any

import numpy as np

from netsim.nr.buffers import SenderBuffer
from netsim.nr.channel import SubbandGains
from netsim.nr.harq import TransportBlock
from netsim.nr.link_adaptation import LinkAdaptation
from netsim.radio_cell import LOSS_BUFFER, LOSS_CHANNEL, LOSS_DELAY_BUDGET


class CellCounters:
    """Counters of a cell of ``n_ue`` UEs whose MCS table goes up to index ``top_mcs``. The
    other parts of the cell add to the fields directly; per link they are keyed ``ul``/``dl``."""

    def __init__(self, n_ue: int, top_mcs: int) -> None:
        self.slots = 0
        self.ul_bytes = [0] * n_ue  # IP bytes delivered, per UE
        self.dl_bytes = [0] * n_ue
        self.ul_prb_used = 0
        self.dl_prb_used = 0
        self.mcs_hist = {"ul": [0] * (top_mcs + 1), "dl": [0] * (top_mcs + 1)}
        self.first_tx = {"ul": 0, "dl": 0}
        self.first_fail = {"ul": 0, "dl": 0}
        self.retx = {"ul": 0, "dl": 0}
        self.residual = {"ul": 0, "dl": 0}
        self.delivered = {"ul": 0, "dl": 0}  # packets
        self.lost = {LOSS_BUFFER: 0, LOSS_DELAY_BUDGET: 0, LOSS_CHANNEL: 0}
        self.pdcch_missed = 0
        self.ul_peak = [0] * n_ue  # largest buffer occupancy seen, bytes per UE
        self.dl_peak = [0] * n_ue

    def account(self, link: str, u: int, tb: TransportBlock, ok: bool, la: LinkAdaptation,
                ack: bool) -> None:
        """A transmission of ``tb`` to or from UE index ``u`` on ``link`` (``ul``/``dl``),
        decoded if ``ok``, read by the gNB as an ACK if ``ack``. First transmissions feed the MCS
        histogram, the first-transmission BLER and ``la``'s outer loop (with the ACK as the gNB
        read it); later ones count as retransmissions."""
        if tb.tx_count == 1:
            self.first_tx[link] += 1
            self.mcs_hist[link][tb.mcs] += 1
            if not ok:
                self.first_fail[link] += 1
            la.feedback(u, ack)
        else:
            self.retx[link] += 1

    def report(self, slot_us: int, n_prb: int, ue_ids: list[str], ul_buf: list[SenderBuffer],
               dl_buf: list[SenderBuffer], la_ul: LinkAdaptation, la_dl: LinkAdaptation,
               channel: SubbandGains) -> dict[str, Any]:
        """``NrCell.stats()``: cell totals, per-link HARQ/LA figures and per-UE bytes and
        buffers. ``slot_us``: slot duration (us); ``n_prb``: PRBs of the carrier; ``ue_ids``:
        the UE names by index; ``ul_buf``/``dl_buf``, ``la_ul``/``la_dl``: the sender buffers
        and link adaptation of each link, by UE index; ``channel``: the cell's channel."""
        slots = max(1, self.slots)
        links: dict[str, Any] = {}
        for link in ("ul", "dl"):
            first = self.first_tx[link]
            bufs = ul_buf if link == "ul" else dl_buf
            la = la_ul if link == "ul" else la_dl
            links[link] = {
                "delivered_bytes": sum(self.ul_bytes if link == "ul" else self.dl_bytes),
                "delivered_packets": self.delivered[link],
                "prb_utilisation": (self.ul_prb_used if link == "ul" else self.dl_prb_used)
                / (slots * n_prb),
                "mcs_histogram": list(self.mcs_hist[link]),
                "first_transmissions": first,
                "bler_first_transmission": self.first_fail[link] / first if first else 0.0,
                "harq_retransmissions": self.retx[link],
                "harq_residual_failures": self.residual[link],
                "buffer_bytes": sum(b.bytes for b in bufs),
                "buffer_peak_bytes_max_ue": max(self.ul_peak if link == "ul" else self.dl_peak),
                "olla_offset_db_mean": float(np.mean(la.offset_db)),
            }
        return {
            "slots": self.slots,
            "slot_us": slot_us,
            "n_prb": n_prb,
            "lost_packets": dict(self.lost),
            "pdcch_missed": self.pdcch_missed,
            "ul": links["ul"],
            "dl": links["dl"],
            "ues": {
                ue: {
                    "ul_delivered_bytes": self.ul_bytes[u],
                    "dl_delivered_bytes": self.dl_bytes[u],
                    "ul_buffer_bytes": ul_buf[u].bytes,
                    "dl_buffer_bytes": dl_buf[u].bytes,
                    "ul_buffer_peak_bytes": self.ul_peak[u],
                    "dl_buffer_peak_bytes": self.dl_peak[u],
                    "los": bool(channel.los[u]),
                    "distance_m": float(channel.d3d_m[u]),
                    "ul_snr_fullband_db": float(channel.ul_snr_fullband_db[u]),
                    "dl_snr_db": float(channel.dl_snr_db[u]),
                    "ul_olla_offset_db": la_ul.offset_db[u],
                    "dl_olla_offset_db": la_dl.offset_db[u],
                }
                for u, ue in enumerate(ue_ids)
            },
        }
