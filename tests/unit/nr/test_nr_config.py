"""NrConfig: calibrated defaults, validation messages, documentation of every field."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from scenario.nr import NrConfig


def test_derived_slot_timing_and_resource_elements() -> None:
    cfg = NrConfig()
    assert cfg.slot_us == 1000 and cfg.subcarrier_spacing_hz == 15000
    assert (cfg.dl_ctrl_symbols, cfg.dl_data_symbols, cfg.guard_symbols, cfg.ul_data_symbols,
            cfg.ul_ctrl_symbols) == (1, 4, 1, 7, 1)
    assert cfg.ul_re_per_prb == 72 and cfg.dl_re_per_prb == 36
    assert cfg.carrier_frequency_hz == 3.5e9 and cfg.mcs_table == "qam64"
    assert NrConfig(subcarrier_spacing_hz=30000, n_prb=200).slot_us == 500


def test_every_field_is_described() -> None:
    for name, field in NrConfig.model_fields.items():
        assert field.description, name


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"ul_data_symbols": 8}, "a slot has 14 symbols"),
    ({"n_prb": 600}, "bandwidth_hz"),
    ({"dl_data_symbols": 1, "ul_data_symbols": 10}, "dl_data_symbols=1 leaves no data RE"),
    ({"mcs_table": "qam256", "max_mcs": 28}, "max_mcs=28"),
    ({"scheduler": "fifo"}, "scheduler"),
    ({"n_prbs": 100}, "n_prbs"),
    ({"olla_min_offset_db": 3.0, "olla_max_offset_db": 1.0}, "olla_min_offset_db"),
])
def test_bad_values_are_rejected_with_the_field_named(kwargs: dict, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        NrConfig(**kwargs)
