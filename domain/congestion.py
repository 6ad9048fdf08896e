"""What the Edge can know of its radio cell's load (and its own CPU's), from the frames it
receives and estimates: each loop's frame delay and loss, the queueing delay over its loops, and
the load control built on them:
every loop gets PDP 1 while the cell has headroom, and a cap holds the injected traffic near
what the cell delivers past its capacity (docs/policy.md, "Load control").
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import astuple, dataclass

# Smoothing of the per-loop estimates, per frame: about the last ten frames weigh.
LOOP_ALPHA = 0.1
# Smoothing of the cell-wide queueing delay and loss, per policy period: about the last half
# second weighs.
CELL_ALPHA = 0.3
# "Complete" below: estimated at the Edge (its last packet in, then its pose job; 4-8 ms at the
# default Edge profiles, 35 ms or more below about 0.12 cpu, which then eats into STALL_US).
# A frame that started to arrive and is still incomplete this long after is counted lost (below
# capacity a frame completes within tens of ms of its first packet), and so is a frame the camera
# sent that has not started to arrive this long after a later one did (its packets were
# discarded whole at the UE, overflowed or failed HARQ; a frame overtaken by a later one in
# HARQ arrives within tens of ms).
LOST_AFTER_US = 250_000
# A frame expected (started to arrive, or shown sent) and still incomplete this long after has
# stalled: below capacity a frame's packets all arrive within 20 ms of its first (17 ms at most
# at 16 loops of a 0.5 m/s cell), its estimate a pose job later. Stalled frames show an overload
# within a period or two of its onset, where the loss shows only LOST_AFTER_US later and the
# delay only of frames that complete (in overload hardly any); the slow start ends on them
# (below).
STALL_US = 50_000
# The cap also takes the cell as past capacity when more than this share of the frames the
# cameras sent never complete (discarded late, overflowed or failed HARQ, whole or in part): deep
# in overload few frames complete, and their delays alone say little. The share counts every
# sent frame, so it bounds what the cameras inject at 1 / (1 - LOSS_TARGET) of what the cell
# delivers: 1.11x.
LOSS_TARGET = 0.1
# Both levels fall by CUT when their delay target is exceeded, at most once per HOLD_US (the
# delay answers a cut only after the queued frames have drained), and climb back a policy period
# while the delay is under it: the fill by STEP (additive increase, multiplicative decrease), the
# cap by STEP of its value. Past capacity the cap sits where the cell's delivery matches it,
# 0.15 at 128 loops; rising by a fixed STEP there would add half again in the ~300 ms a loss
# takes to show (LOST_AFTER_US), rising in proportion adds 6 % as near 1.
CUT = 0.85
HOLD_US = 300_000
# The cap is also cut at least to the share of the frames that arrive (1 - loss), applied to the
# cap those frames were sent under: deep past capacity a cut or two then bring what the cameras
# send near what the cell delivers, where a dozen cuts by CUT took 3 s at 128 loops while every
# queue grew. The frames whose loss the Edge reads were sent about LOSS_LAG_US before: a frame
# is known sent when a later one of its loop arrives (past capacity a loop's frames arrive a few
# hundred ms apart), counted lost LOST_AFTER_US after that, and the cell's loss weighs about
# the last three periods. As the lag varies, no cut goes below DEEPEST_CUT of the cap.
LOSS_LAG_US = 600_000
DEEPEST_CUT = 0.5
STEP = 0.01
# Where every loop at the cap's least PDP still overloads the cell well past its capacity, the
# load control sheds loops instead of lowering that PDP: a lower PDP for all would starve every
# loop of frames, where serving fewer loops keeps those served at a PDP that places their tasks.
# Only well past: a loss spread over every loop costs fewer tasks than shedding some (at 192
# loops of the default cell about 15 % of the frames are lost at the least cap and 90 % of the
# tasks placed; shedding to a loss of LOSS_TARGET placed 79 %), while at 240 loops some 30 % are
# lost, estimates go stale and 29 % are placed. So loops are shed only once the cap has sat at its
# least for SHED_AFTER_US (the loss read then is of frames sent at it, past the start's
# transient) and more than SHED_LOSS_TARGET of the frames are lost, with the cap's rule (cut,
# climb by STEP of its value), down to LEAST_SERVED of the loops; while any loop is shed the cap
# holds, and the loops come back before any PDP rises.
SHED_LOSS_TARGET = 0.25
SHED_AFTER_US = 1_000_000
LEAST_SERVED = 0.05
# A run's Edge knows nothing of its cell's capacity yet: its cap starts low (the policy's
# `guard_start_pdp`) and doubles every period until the first sign of congestion (TCP's slow
# start, RFC 5681). Starting every loop at PDP 1 puts a cell past capacity into overload for the
# half second its loss takes to show; the UEs then discard the tail of every frame at its delay
# budget, so hardly a frame completes (at 40 loops of a 0.5 m/s cell, a camera's first to
# complete after 0.08 s was captured at 0.74 s) and parts landing meanwhile on a fast belt
# cross unseen. Below capacity the cap reaches 1 within four periods. Doubling, the start
# overshoots: frames sent past capacity stall (STALL_US) some 150 ms later, by when the cap has
# doubled twice more or reached 1 (at 40 loops of a 0.5 m/s cell, sent at 0.8 from 150 ms,
# stalled from 300 ms). So the start watches for stalled frames until the cap has been 1 for
# START_WATCH_US, ends on more than LOSS_TARGET of them stalled, and then cuts to half the cap in
# force START_LAG_US before, under which the stalled frames were sent (TCP's halving of the
# window in force at the loss). The frames lost in that overload are read as loss only from about
# LOSS_LAG_US later, when the start's cut has mostly answered them: for LOSS_LAG_US after it, a
# loss cuts nothing (TCP's fast recovery, RFC 6582: one cut per episode of loss); the queueing
# delay still cuts past its target. Cut again by that loss, the cap fell to half what the cell
# carries (at 56 loops of a 0.5 m/s cell, seed 2: from 0.21 to 0.11, which starved every loop of
# frames).
START_LAG_US = 100_000
START_WATCH_US = 200_000
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def served_rank(loop: int) -> float:
    """Where ``loop`` (its index) ranks among the loops to serve, in [0, 1): a loop is served
    while the share served exceeds it. The fractional part of the index times the golden ratio's
    inverse: the loops served at a share are a subset of those served at any larger share (a
    rising share sheds no loop), about the share of any run of indices (so spread over the hall)."""
    return (loop * _GOLDEN) % 1.0


@dataclass(frozen=True)
class LinkEstimate:
    """The uplink as one loop's Edge sees it: ``delay_s`` smoothed capture-to-estimate delay of
    its frames (s: the frame's arrival and the Edge's estimation of it), ``loss`` smoothed share
    of its frames that started to arrive and were never estimated; ``cell_queueing_s`` and
    ``cell_loss`` the queueing delay (delay above each loop's smallest, s) and loss over every
    loop of the Edge: the load of the cell and of the Edge's CPU."""

    delay_s: float = 0.0
    loss: float = 0.0
    cell_queueing_s: float = 0.0
    cell_loss: float = 0.0


IDLE_LINK = LinkEstimate()


@dataclass(frozen=True)
class PeriodCounts:
    """What a monitor saw of an Edge's frames over one policy period: the sum of their queueing
    delays (s) and how many completed, were counted lost and had stalled at its end."""

    queued_s: float
    frames: int
    lost: int
    stalled: int


class UplinkMonitor:
    """Smoothed uplink delay and loss of the frames an Edge receives, per loop and cell-wide.

    The cell's load shows as queueing delay: a frame's delay above the smallest its loop has
    seen (the base delay: capture, compression, an empty cell's transmission, the estimation),
    as delay-based congestion control (LEDBAT, RFC 6817) measures it. ``frame`` is called as a
    frame's estimate is ready, so that the Edge's own compute queue shows as the cell's does,
    ``lost`` as a frame is given up; ``period`` once per policy period folds that period's frames
    into the cell-wide figures (a period with no frame keeps them). A frame that ``started`` to
    arrive and has no estimate LOST_AFTER_US later is counted ``lost``.

    Frames are known by their loop's sent-frame sequence number (``seq``: 0, 1, 2, ... over the
    frames its camera sent; a frame the camera dropped on purpose, PDP, takes none). A frame
    that arrives past a gap in the sequence shows that the camera sent the missing ones: each is
    expected from then on, and counted lost unless it started to arrive within LOST_AFTER_US, so
    that frames discarded whole before reaching the Edge (past capacity, most of them) count as
    lost too. A frame seen before (a duplicate, or one already counted lost) starts nothing."""

    def __init__(self) -> None:
        self.delay_s: dict[int, float] = {}
        self.base_s: dict[int, float] = {}
        self.loss: dict[int, float] = {}
        self.cell_queueing_s = 0.0
        self.cell_loss = 0.0
        self.stalled = 0.0  # share of the frames expected, at the last period, that have stalled
        self._sum_s = 0.0
        self._n = 0
        self._lost = 0
        # (loop, seq) of each frame expected and not complete -> since when (us): its first
        # packet's arrival, or when a later frame showed it was sent.
        self._partial: dict[tuple[int, int], int] = {}
        self._unstarted: set[tuple[int, int]] = set()  # of those, shown sent and not started
        self._next: dict[int, int] = {}  # per loop: the sequence number after the highest seen

    def _seen(self, loop: int, seq: int, now_us: int) -> bool:
        """Frame ``seq`` of ``loop`` seen at ``now_us`` (us): the frames sent before it and not
        seen yet are expected from now. False when it was seen before and is no longer
        expected (complete, or counted lost)."""
        nxt = self._next.get(loop, 0)
        if seq < nxt:
            return (loop, seq) in self._partial
        for missing in range(nxt, seq):
            self._partial[(loop, missing)] = now_us
            self._unstarted.add((loop, missing))
        self._next[loop] = seq + 1
        return True

    def started(self, loop: int, seq: int, now_us: int) -> None:
        """The first packet of sent frame ``seq`` of ``loop`` arrived at ``now_us`` (us): from
        now it has LOST_AFTER_US to complete (also when a later frame showed it sent before)."""
        if self._seen(loop, seq, now_us):
            key = (loop, seq)
            if key in self._unstarted:
                self._unstarted.discard(key)
                self._partial[key] = now_us
            else:
                self._partial.setdefault(key, now_us)

    def frame(self, loop: int, capture_us: int, estimated_us: int, seq: int | None = None) -> None:
        """Sent frame ``seq`` of ``loop`` (None: not numbered, no gap is looked for) captured at
        ``capture_us`` (us) estimated at the Edge at ``estimated_us`` (us: its last packet in
        and its estimation done) (a frame already counted lost counts as estimated too: it was
        late)."""
        if seq is not None:
            self._seen(loop, seq, estimated_us)
            self._partial.pop((loop, seq), None)
            self._unstarted.discard((loop, seq))
        d = max(0, estimated_us - capture_us) / 1e6
        last = self.delay_s.get(loop, d)
        self.delay_s[loop] = last + LOOP_ALPHA * (d - last)
        self.loss[loop] = self.loss.get(loop, 0.0) * (1 - LOOP_ALPHA)
        base = min(self.base_s.get(loop, d), d)
        self.base_s[loop] = base
        self._sum_s += d - base
        self._n += 1

    def dropped(self, loop: int, seq: int) -> None:
        """Sent frame ``seq`` of ``loop``, complete, dropped at the Edge without an estimate (a
        newer frame of the loop took its place while it waited for the CPU): lost, counted now."""
        if self._partial.pop((loop, seq), None) is not None:
            self._unstarted.discard((loop, seq))
            self.lost(loop)

    def lost(self, loop: int) -> None:
        """A frame of ``loop`` sent and never (completely) received."""
        self.loss[loop] = self.loss.get(loop, 0.0) + LOOP_ALPHA * (1.0 - self.loss.get(loop, 0.0))
        self._lost += 1

    def period(self, now_us: int) -> tuple[float, float]:
        """Fold the frames since the last call into the cell's queueing delay (s) and loss (share
        of frames), which it returns; at ``now_us`` (us), a frame expected LOST_AFTER_US ago
        (started, or shown sent by a later one) and still incomplete counts as lost. ``stalled``
        becomes the share of the frames expected STALL_US ago or more and still incomplete among
        those and the frames completed since the last call (not smoothed: the start's signal)."""
        return self.fold([self.close(now_us)])

    def close(self, now_us: int) -> PeriodCounts:
        """The counts of the frames since the last call, as ``period`` folds them at ``now_us``
        (us); the next call counts from here."""
        stalled = sum(1 for first in self._partial.values() if now_us - first >= STALL_US)
        for key in [k for k, first in self._partial.items() if now_us - first >= LOST_AFTER_US]:
            del self._partial[key]
            self._unstarted.discard(key)
            self.lost(key[0])
        counts = PeriodCounts(self._sum_s, self._n, self._lost, stalled)
        self._sum_s, self._n, self._lost = 0.0, 0, 0
        return counts

    def fold(self, counts: Iterable[PeriodCounts]) -> tuple[float, float]:
        """Fold a period's ``counts`` (``close``: this monitor's own, and those of the other
        monitors watching the same Edge's frames) into the cell's queueing delay (s) and loss
        (share of frames), which it returns, and the share of frames ``stalled``. The counts are
        summed in an order of their own, so every monitor given the same counts folds the same
        figures."""
        ordered = sorted(counts, key=astuple)
        sum_s = sum(c.queued_s for c in ordered)
        n = sum(c.frames for c in ordered)
        lost = sum(c.lost for c in ordered)
        stalled = sum(c.stalled for c in ordered)
        self.stalled = stalled / (stalled + n) if stalled else 0.0
        if n:
            self.cell_queueing_s += CELL_ALPHA * (sum_s / n - self.cell_queueing_s)
        if n or lost:
            self.cell_loss += CELL_ALPHA * (lost / (n + lost) - self.cell_loss)
        return self.cell_queueing_s, self.cell_loss

    def estimate(self, loop: int) -> LinkEstimate:
        """The uplink as the Edge sees it for ``loop``, and the cell's load."""
        return LinkEstimate(self.delay_s.get(loop, 0.0), self.loss.get(loop, 0.0), self.cell_queueing_s,
                            self.cell_loss)


class Level:
    """A PDP level in [``low``, 1] steered by a delay target: cut by CUT when the cell's queueing
    delay exceeds ``target_s`` (s) (or its loss exceeds ``loss_target``, a share of frames), at
    most once per HOLD_US; raised by STEP a period otherwise (``proportional``: by STEP of its
    value). A level steered by the loss is cut to the lesser of CUT of its value and the share
    of the frames that arrive times the level in force LOSS_LAG_US before, when they were sent
    (after a climb, that level is the last one known to be carried), never below DEEPEST_CUT of
    its value. A level that begins under 1 (``start``) doubles every period instead until it is
    first cut or reaches 1 (a slow start); for LOSS_LAG_US after the start's cut, the loss of the
    frames sent before it cuts nothing more."""

    def __init__(self, target_s: float, low: float, loss_target: float = 1.0, proportional: bool = False,
                 start: float = 1.0) -> None:
        self.target_s = target_s
        self.low = low
        self.loss_target = loss_target
        self.proportional = proportional
        self.value = start
        self._start = start
        self._starting = start < 1.0
        self._full_us: int | None = None  # when the start reached 1
        self._last_cut_us: int | None = None
        self._start_cut_us: int | None = None  # when the start ended in a cut
        # (time, value) of the last LOSS_LAG_US and the last value before them, oldest first
        # (kept for a level steered by the loss).
        self._past: deque[tuple[int, float]] = deque()

    def _value_at(self, t_us: int) -> float:
        """The level in force at ``t_us`` (us), at most LOSS_LAG_US ago (its start before the
        first period)."""
        before = self._start
        for t, v in self._past:
            if t > t_us:
                break
            before = v
        return before

    def update(self, now_us: int, queueing_s: float, loss: float, stalled: float = 0.0) -> None:
        """One policy period ending at ``now_us`` (us, never before the last call's) with the
        cell's queueing delay ``queueing_s`` (s), loss ``loss`` and stalled frames ``stalled``
        (shares of frames)."""
        loss = 1.0 if math.isnan(loss) else min(1.0, max(0.0, loss))  # a share; NaN: nothing known to arrive
        starting = self._starting
        recovering = self._start_cut_us is not None and now_us - self._start_cut_us < LOSS_LAG_US
        if (queueing_s > self.target_s or (loss > self.loss_target and not recovering)
                or (starting and stalled > self.loss_target)):
            self._starting = False
            if self._last_cut_us is None or now_us - self._last_cut_us >= HOLD_US:
                cut = self.value * CUT
                if self.loss_target < 1.0:  # to what the cell delivers (LOSS_LAG_US)
                    delivered = self._value_at(now_us - LOSS_LAG_US) * (1.0 - loss)
                    cut = min(cut, max(self.value * DEEPEST_CUT, delivered))
                if starting:  # the start overshot: half what the stalled frames were sent under
                    cut = min(cut, self._value_at(now_us - START_LAG_US) * DEEPEST_CUT)
                    self._start_cut_us = now_us
                self.value = max(self.low, cut)
                self._last_cut_us = now_us
        elif self._starting:
            self.value = min(1.0, 2.0 * self.value)
            if self.value == 1.0 and self._full_us is None:
                self._full_us = now_us
            self._starting = self._full_us is None or now_us - self._full_us < START_WATCH_US
        else:
            self.value = min(1.0, self.value * (1 + STEP) if self.proportional else self.value + STEP)
        if self.loss_target < 1.0:  # only a level steered by the loss looks back
            self._past.append((now_us, self.value))
            while len(self._past) > 1 and self._past[1][0] <= now_us - LOSS_LAG_US:
                self._past.popleft()


class LoadControl:
    """The cell-wide part of every co-design policy's PDP (docs/policy.md, "Load control"):

    - ``fill``: the PDP every loop may use for free, 1 while the cell's queueing delay stays under
      ``headroom_s`` (s; traffic costs nothing while the cell has headroom), falling as the cell
      nears saturation so that the policy's own PDP takes over (None: off);
    - ``cap``: the PDP no loop may exceed: from ``start_cap``, doubled every period up to 1 (a
      slow start), until the queueing delay passes ``cap_s`` (s) or the frame loss LOSS_TARGET,
      then cut so that the injected traffic stays near what the cell delivers instead of every
      queue growing (None: off); never under ``min_cap``;
    - ``served``: the share of the loops served (``serves``), 1 until every loop at
      ``min_cap`` still loses more than SHED_LOSS_TARGET of its frames, then cut and raised by
      the frame loss as the cap is, down to LEAST_SERVED; the loops not served send nothing.

    Below capacity the delay stays under both targets: after the start every loop sends at
    PDP 1, as with no co-design at all."""

    def __init__(self, headroom_s: float | None, cap_s: float | None, min_cap: float,
                 start_cap: float = 1.0) -> None:
        self._fill = Level(headroom_s, 0.0) if headroom_s is not None else None
        self._cap = (Level(cap_s, min_cap, LOSS_TARGET, proportional=True, start=max(start_cap, min_cap))
                     if cap_s is not None else None)
        self._served = Level(math.inf, LEAST_SERVED, SHED_LOSS_TARGET, proportional=True)  # the loss alone
        self._least_since_us: int | None = None  # since when the cap has been at min_cap

    @property
    def fill(self) -> float:
        """The PDP every loop may use for free now (0: off)."""
        return self._fill.value if self._fill is not None else 0.0

    @property
    def cap(self) -> float:
        """The PDP no loop may exceed now (1: off)."""
        return self._cap.value if self._cap is not None else 1.0

    @property
    def served(self) -> float:
        """The share of the loops served now (1: every loop)."""
        return self._served.value

    def serves(self, loop: int) -> bool:
        """Whether ``loop`` (its index) is served now: its rank under the share served."""
        return served_rank(loop) < self.served

    def update(self, now_us: int, queueing_s: float, loss: float, stalled: float = 0.0) -> None:
        """One policy period ending at ``now_us`` (us) whose smoothed queueing delay is
        ``queueing_s`` (s), loss ``loss`` and stalled frames ``stalled`` (shares of frames)."""
        if self._fill is not None:
            self._fill.update(now_us, queueing_s, 1.0)
        if self._cap is None:
            return
        least = self._least_since_us
        if self._served.value < 1.0 or (least is not None and now_us - least >= SHED_AFTER_US
                                        and loss > SHED_LOSS_TARGET):
            self._served.update(now_us, queueing_s, loss)
        else:
            self._cap.update(now_us, queueing_s, loss, stalled)
        if self._cap.value > self._cap.low:
            self._least_since_us = None
        elif least is None:
            self._least_since_us = now_us
