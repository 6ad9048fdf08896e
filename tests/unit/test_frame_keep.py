"""The camera's keep decisions (domain/frame_keep.py): Bernoulli as the cameras always drew them,
spaced with bounded gaps and the same share."""

from __future__ import annotations

import numpy as np
import pytest

from domain.frame_keep import FrameKeep
from scenario.schema import ScenarioError, parse_scenario


def test_bernoulli_draws_what_the_cameras_drew() -> None:
    """One draw a frame, kept below the PDP: the stream and the decisions of before."""
    keeper, ref = FrameKeep("bernoulli", np.random.default_rng(5)), np.random.default_rng(5)
    pdps = [1.0, 0.3, 0.3, 0.0, 0.7] * 200
    assert [keeper.keep(p) for p in pdps] == [bool(ref.random() < p) for p in pdps]


@pytest.mark.parametrize("pdp", [0.2, 0.3, 0.45, 0.9])
def test_spaced_keeps_the_share_with_no_long_gap(pdp: float) -> None:
    keeper = FrameKeep("spaced", np.random.default_rng(1))
    kept = [keeper.keep(pdp) for _ in range(3000)]
    assert abs(sum(kept) / len(kept) - pdp) < 1e-3
    at = np.flatnonzero(kept)
    assert int(np.diff(at).max()) <= int(np.ceil(1 / pdp))
    # Bernoulli at the same PDP leaves gaps many times longer (30 fps: seconds without a frame).
    ref = np.random.default_rng(1).random(3000) < pdp
    assert int(np.diff(np.flatnonzero(ref)).max()) > int(np.ceil(1 / pdp))


def test_spaced_keeps_each_frame_with_probability_pdp_over_the_phases() -> None:
    """Over many cameras (phases drawn from their streams), the k-th frame is kept at the PDP."""
    share = np.mean([[k.keep(0.25) for _ in range(8)]
                     for k in (FrameKeep("spaced", np.random.default_rng(s)) for s in range(4000))], axis=0)
    assert np.all(np.abs(share - 0.25) < 0.03)


def test_spaced_follows_the_pdp_as_it_changes() -> None:
    keeper = FrameKeep("spaced", np.random.default_rng(2))
    assert all(keeper.keep(1.0) for _ in range(50))
    assert not any(keeper.keep(0.0) for _ in range(50))
    kept = [keeper.keep(0.5) for _ in range(100)]
    assert sum(kept) == 50


def test_keep_mode_is_a_camera_setting() -> None:
    assert parse_scenario({}).camera.frame_keep == "bernoulli"
    assert parse_scenario({"camera": {"frame_keep": "spaced"}}).camera.frame_keep == "spaced"
    with pytest.raises(ScenarioError, match="frame_keep"):
        parse_scenario({"camera": {"frame_keep": "even"}})
