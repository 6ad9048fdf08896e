"""The SINR of the transmissions of one slot and link direction in a hall with several gNBs: per
PRB, the serving link's signal over the noise plus every co-channel transmission of another cell
on that PRB, then the EESM over the transmission's PRBs. Vectorised over the transmissions and
over the PRB segments they share (PRBs where the set of transmissions and the subband are the
same), with no loop over PRBs; PRBs no transmission uses cost nothing."""

from __future__ import annotations

import numpy as np

from netsim.nr.link_fading import LinkFading


def slot_sinr(p0: np.ndarray, n: np.ndarray, scale: np.ndarray, beta: np.ndarray,
              serving: np.ndarray, cross_inr: np.ndarray, cross_links: np.ndarray,
              fading: LinkFading, update: int, subband_prb: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Effective SINR (linear) of each of T transmissions and the mean interference over noise
    (linear) on its PRBs, arrays (T,).

    Transmission i uses PRBs [``p0[i]``, ``p0[i]`` + ``n[i]``) with a mean SNR per PRB
    ``scale[i]`` (linear, before fading) over its serving link ``serving[i]`` (a link of
    ``fading``, brought to grid update ``update``) and EESM beta ``beta[i]``.
    ``cross_inr[i, j]`` (T, T) is the interference over noise per PRB (linear, before fading)
    transmission j causes at i's receiver over link ``cross_links[i, j]``: 0 where it causes
    none (the same cell, another frequency group). Subbands are ``subband_prb`` PRBs.
    """
    end = p0 + n
    # Segments: cut at every allocation edge and every subband edge in between.
    lo = int(p0.min())
    last = int(end.max())
    cut = np.zeros(last + 1, dtype=bool)
    cut[p0] = True
    cut[end] = True
    cut[subband_prb * (lo // subband_prb + 1):last:subband_prb] = True
    edges = np.flatnonzero(cut)
    starts = edges[:-1]
    lengths = np.diff(edges).astype(float)
    sb = starts // subband_prb
    t = p0.size
    overlap = cross_inr > 0
    # Every transmission on the same PRBs (a loaded hall's usual slot): each is on every
    # segment, which spares the masks below (a product by True, a sum of zeros: the same numbers).
    whole = bool((p0 == lo).all()) and bool((end == last).all())
    active: np.ndarray | None = None
    if not whole:
        active = (p0[:, None] <= starts[None, :]) & (starts[None, :] < end[:, None])
        overlap &= (p0[:, None] < end[None, :]) & (p0[None, :] < end[:, None])
    pairs = np.flatnonzero(overlap)  # victim i * t + interferer j, in row order
    pair_links = cross_links.ravel().take(pairs)
    fading.refresh(np.concatenate((serving, pair_links)), update)
    gain = fading.gain
    # Rows of the gains by link (take), then the segments' subbands unless they are every one.
    every_subband = sb.size == gain.shape[1] and int(sb[0]) == 0 and int(sb[-1]) == sb.size - 1
    # In double precision before the products (exact), which then need no casting on the way.
    rows = gain.take(serving, axis=0).astype(float)
    sinr: np.ndarray = scale[:, None] * (rows if every_subband else rows[:, sb])
    inr = np.zeros(sinr.shape)
    if pairs.size:
        pairs_i = pairs // t
        rows = gain.take(pair_links, axis=0).astype(float)
        contrib = cross_inr.ravel().take(pairs)[:, None] * (rows if every_subband
                                                           else rows[:, sb])
        if active is not None:
            contrib *= active.astype(float).take(pairs - pairs_i * t, axis=0)
        # Pairs come in row order: one sum per victim over its interferers.
        first = np.flatnonzero(np.diff(pairs_i, prepend=-1))
        inr[pairs_i[first]] = np.add.reduceat(contrib, first, axis=0)
        sinr = sinr / (1.0 + inr)
    nf = n.astype(float)
    # exp(-rel / beta) below as exp(rel / -beta): the same quotient (division is symmetric in
    # sign), one negation per transmission rather than per segment.
    if active is None:
        smin = sinr.min(axis=1)
        rel = sinr - smin[:, None]
        acc = (np.exp(rel / -beta[:, None]) * lengths).sum(axis=1)
        eff = smin - beta * np.log(acc / nf)
        return eff, (inr * lengths).sum(axis=1) / nf
    weights = np.where(active, lengths[None, :], 0.0)
    smin = np.where(active, sinr, np.inf).min(axis=1)
    # EESM relative to the smallest SINR (no overflow), over the transmission's own segments.
    rel = np.where(active, sinr, smin[:, None]) - smin[:, None]
    acc = (np.exp(rel / -beta[:, None]) * weights).sum(axis=1)
    eff = smin - beta * np.log(acc / nf)
    return eff, (inr * weights).sum(axis=1) / nf
