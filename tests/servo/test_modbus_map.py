"""Modbus register map: the default layout, word order, value ranges, TOML loading and its errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.servo.modbus_map import (
    DEFAULT_MAP_PATH,
    ModbusMapError,
    RegisterMap,
    default_map,
    load_map,
)
from drivers.servo.modbus_rtu import ModbusError

REPO = Path(__file__).resolve().parents[2]


def test_default_map_follows_the_documented_address_rule() -> None:
    m = default_map()
    assert m.word_order == "high_first"
    for e in m.entries:
        assert e.address == (e.index & 0xF000) + ((e.index & 0xFF) << 4) + 2 * e.subindex, e.name
    # the objects a position servo needs are all there
    for index in (0x6040, 0x6041, 0x6060, 0x6061, 0x607A, 0x6081, 0x6083, 0x6084, 0x6064, 0x606C, 0x603F,
                  0x6098, 0x60FF, 0x1001):  # fmt: skip
        assert (index, 0) in m
    assert m.entry(0x6040).address == 0x6400
    assert m.entry(0x6041).address == 0x6410
    assert m.entry(0x6064).address == 0x6640 and m.entry(0x6064).count == 2
    assert m.entry(0x6099, 2).address == 0x6994


def test_sample_block_mirrors_status_and_position_contiguously() -> None:
    m = default_map()
    assert m.sample is not None
    names = [e.name for e in m.covering(m.sample.address, m.sample.count)]
    assert names == ["sample.statusword", "sample.error_code", "sample.position_actual_value",
                     "sample.velocity_actual_value"]  # fmt: skip
    assert all(not e.writable for e in m.sample.entries)


def test_word_order_high_first_and_low_first() -> None:
    m = default_map()
    e = m.entry(0x607A)
    assert m.encode(e, 0x12345678) == (0x1234, 0x5678)
    assert m.encode(e, -2) == (0xFFFF, 0xFFFE)
    low = RegisterMap(entries=m.entries, word_order="low_first")
    assert low.encode(e, 0x12345678) == (0x5678, 0x1234)
    assert low.decode(e, (0x5678, 0x1234)) == 0x12345678


def test_eight_bit_objects_are_sign_extended_into_one_register() -> None:
    m = default_map()
    mode = m.entry(0x6060)
    assert m.encode(mode, -1) == (0xFFFF,)
    assert m.decode(mode, (0xFFFF,)) == -1
    assert m.decode(mode, (6,)) == 6
    with pytest.raises(ModbusMapError, match=r"-128\.\.127"):
        m.decode(mode, (0x0080,))  # 128 does not fit an i8
    with pytest.raises(ModbusMapError):
        m.encode(mode, 200)


@given(st.sampled_from(default_map().entries), st.data())
def test_encode_decode_round_trip_in_both_word_orders(entry: object, data: st.DataObject) -> None:
    from drivers.servo.modbus_map import _TYPES

    assert hasattr(entry, "type")
    _, lo, hi = _TYPES[entry.type]  # type: ignore[attr-defined]
    value = data.draw(st.integers(lo, hi))
    for order in ("high_first", "low_first"):
        m = RegisterMap(entries=default_map().entries, word_order=order)  # type: ignore[arg-type]
        regs = m.encode(entry, value)  # type: ignore[arg-type]
        assert all(0 <= r <= 0xFFFF for r in regs)
        assert m.decode(entry, regs) == value  # type: ignore[arg-type]


def test_out_of_range_values_are_refused() -> None:
    m = default_map()
    with pytest.raises(ModbusMapError, match="profile_velocity"):
        m.encode(m.entry(0x6081), -1)
    with pytest.raises(ModbusMapError):
        m.encode(m.entry(0x607A), 2**31)
    with pytest.raises(ModbusMapError, match="2 registers"):
        m.decode(m.entry(0x607A), (1,))


def test_covering_rejects_gaps_and_half_objects() -> None:
    m = default_map()
    assert [e.name for e in m.covering(0x6640, 2)] == ["position_actual_value"]
    with pytest.raises(ModbusMapError, match="second half"):
        m.covering(0x6641, 1)
    with pytest.raises(ModbusMapError, match="ends inside"):
        m.covering(0x6640, 1)
    with pytest.raises(ModbusMapError, match="not mapped"):
        m.covering(0x6400, 2)  # controlword then the unmapped 0x6401
    with pytest.raises(ModbusMapError, match="not in the register map"):
        m.entry(0x6502)


def test_decode_block() -> None:
    m = default_map()
    assert m.sample is not None
    values = m.decode_block(m.sample.address, (0x0637, 0, 0xFFFF, 0xFF38, 0, 1000))
    assert {e.name: v for e, v in values.items()} == {
        "sample.statusword": 0x0637,
        "sample.error_code": 0,
        "sample.position_actual_value": -200,
        "sample.velocity_actual_value": 1000,
    }


def test_a_toml_file_replaces_the_default(tmp_path: Path) -> None:
    path = tmp_path / "delta_like.toml"
    path.write_text(
        """
word_order = "low_first"
[[register]]
name = "controlword"
index = 0x6040
address = 0x0100
type = "u16"
[[register]]
name = "statusword"
index = 0x6041
address = 0x0101
type = "u16"
access = "r"
[[register]]
name = "position"
index = 0x6064
address = 0x0102
type = "i32"
access = "r"
[sample]
address = 0x0200
objects = ["statusword", "position"]
"""
    )
    m = load_map(path)
    assert m.word_order == "low_first"
    assert m.entry(0x6040).address == 0x0100 and m.entry(0x6040).writable
    assert (0x607A, 0) not in m
    with pytest.raises(ModbusMapError, match="0x607A"):
        m.entry(0x607A)
    assert [e.name for e in m.covering(0x0100, 4)] == ["controlword", "statusword", "position"]
    assert m.sample is not None and m.sample.count == 3


BAD_MAPS = [
    ("word_order = 'middle'\n[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'", "word_order"),
    ("", "non-empty"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='f32'", "type must be"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'\nacess='r'", "unknown key"),
    ("[[register]]\nname='a'\nindex=0x6040\ntype='u16'", "missing 'address'"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=0x10000\ntype='u16'", "0..65535"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=0xFFFF\ntype='u32'", "past register"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u32'\n"
     "[[register]]\nname='b'\nindex=0x6041\naddress=2\ntype='u16'", "overlaps"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'\n"
     "[[register]]\nname='a'\nindex=0x6041\naddress=2\ntype='u16'", "defined twice"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'\n"
     "[[register]]\nname='b'\nindex=0x6040\naddress=2\ntype='u16'", "mapped twice"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'\n[sample]\naddress=9\nobjects=['zz']", "zz"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'\naccess='w'\n[sample]\naddress=9\n"
     "objects=['a']", "write-only"),
    ("[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'\n[sample]\naddress=1\nobjects=['a']", "overlaps"),
    ("[[register]\nname='a'", "not valid TOML"),
    ("colour = 'red'\n[[register]]\nname='a'\nindex=0x6040\naddress=1\ntype='u16'", "unknown top-level"),
]  # fmt: skip


@pytest.mark.parametrize(("text", "message"), BAD_MAPS)
def test_bad_map_files_give_clear_typed_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ModbusMapError, match=message) as info:
        load_map(path)
    assert isinstance(info.value, ModbusError)
    assert str(path) in str(info.value) or "not valid TOML" in str(info.value)


def test_missing_map_file(tmp_path: Path) -> None:
    with pytest.raises(ModbusMapError, match="not found"):
        load_map(tmp_path / "nope.toml")


def test_docs_carry_the_default_map_table() -> None:
    doc = (REPO / "docs" / "modbus.md").read_text()
    assert default_map().markdown_table() in doc, "docs/modbus.md is out of step with modbus_map.toml"
    assert DEFAULT_MAP_PATH.is_file()
