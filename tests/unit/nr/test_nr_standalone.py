"""``cosim5g netsim``: the standalone camera scenario and its command line."""

from __future__ import annotations

import json

import pytest

from netsim.standalone import camera_layout, main, radical_inverse
from scenario.nr import NrConfig


def test_layout_is_inside_the_hall_and_stable_in_n() -> None:
    cfg = NrConfig()
    gnb, ues = camera_layout(40, cfg)
    assert gnb == (60.0, 30.0, 1.5)
    assert len(ues) == 40 and len(set(ues.values())) == 40
    for x, y, z in ues.values():
        assert 5 <= x <= 115 and 5 <= y <= 55 and z == 1.5
    assert camera_layout(3, cfg)[1] == {k: ues[k] for k in ("camera-0", "camera-1", "camera-2")}
    assert [radical_inverse(i, 2) for i in (1, 2, 3)] == [0.5, 0.25, 0.75]


def test_json_output_has_the_kpis(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--ues", "3", "--rate-mbps", "6", "--duration-s", "0.4", "--seed", "3",
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["offered_mbps"] == pytest.approx(18.0, rel=1e-3)
    assert result["ul_throughput_mbps"] > 0
    assert set(result["ip_latency_ms"]) >= {"p50", "p99"}
    assert set(result["lost_packets"]) == {"buffer_overflow", "delay_budget", "channel"}
    assert result["slots"] == 400 and result["slots_per_second"] > 0
    # A wrapper may hand over its remainder with the "--" separator still in front.
    assert main(["--", "--ues", "1", "--rate-mbps", "1", "--duration-s", "0.1"]) == 0


@pytest.mark.parametrize(("argv", "named"), [
    (["--ues", "0", "--rate-mbps", "8", "--duration-s", "1"], "--ues"),
    (["--ues", "two", "--rate-mbps", "8", "--duration-s", "1"], "--ues"),
    (["--ues", "2", "--rate-mbps", "-1", "--duration-s", "1"], "--rate-mbps"),
    (["--ues", "2", "--rate-mbps", "8"], "--duration-s"),
    (["--ues", "2", "--rate-mbps", "8", "--duration-s", "1", "--frame-rate", "0"],
     "--frame-rate"),
    (["--ues", "2", "--rate-mbps", "8", "--duration-s", "1", "--set", "n_prb=9999"], "n_prb"),
    (["--ues", "2", "--rate-mbps", "8", "--duration-s", "1", "--set", "nprb=100"], "nprb"),
    # no whole slot after the warm-up to measure a rate over (a division by zero before)
    (["--ues", "1", "--rate-mbps", "8", "--duration-s", "0.5004", "--warmup-s", "0.5"], "--duration-s"),
    (["--ues", "1", "--rate-mbps", "8", "--duration-s", "0.000004"], "--duration-s"),
])
def test_bad_arguments_exit_2_naming_the_field(argv: list[str], named: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert named in capsys.readouterr().err
