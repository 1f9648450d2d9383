"""Modbus register map: where the CiA 402 objects of a servo drive live in its holding registers.

The default map (``modbus_map.toml`` beside this module, documented in ``docs/modbus.md``) lays the CiA
402 objects out as ``address = (index & 0xF000) + ((index & 0xFF) << 4) + 2 * subindex``; a TOML file of the same
shape replaces it for a drive with another layout. The map is shared by the master
(:mod:`drivers.servo.modbus_backend`) and the simulated slave (:mod:`sim.drive.modbus_server`), so both
agree on addresses, data types and the word order of 32-bit values.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

from drivers.servo.modbus_rtu import ModbusError

__all__ = [
    "DEFAULT_MAP_PATH",
    "ModbusMapError",
    "RegisterEntry",
    "RegisterMap",
    "SampleBlock",
    "default_map",
    "load_map",
]

DEFAULT_MAP_PATH: Final = Path(__file__).with_name("modbus_map.toml")

WordOrder = Literal["high_first", "low_first"]
Access = Literal["r", "w", "rw"]

# type -> (registers, minimum, maximum)
_TYPES: Final[dict[str, tuple[int, int, int]]] = {
    "u8": (1, 0, 0xFF),
    "i8": (1, -0x80, 0x7F),
    "u16": (1, 0, 0xFFFF),
    "i16": (1, -0x8000, 0x7FFF),
    "u32": (2, 0, 0xFFFF_FFFF),
    "i32": (2, -0x8000_0000, 0x7FFF_FFFF),
}


class ModbusMapError(ModbusError):
    """A register map that is malformed, or an object or address it does not define, or a value out of range."""


@dataclass(frozen=True)
class RegisterEntry:
    """One CiA 402 object at one register address."""

    name: str
    index: int
    subindex: int
    address: int
    type: str
    access: Access
    description: str = ""

    @property
    def count(self) -> int:
        """Number of 16-bit registers the object occupies (1 or 2)."""
        return _TYPES[self.type][0]

    @property
    def signed(self) -> bool:
        return self.type.startswith("i")

    @property
    def readable(self) -> bool:
        return "r" in self.access

    @property
    def writable(self) -> bool:
        return "w" in self.access

    @property
    def obj(self) -> tuple[int, int]:
        return (self.index, self.subindex)

    def check_value(self, value: int) -> None:
        _, lo, hi = _TYPES[self.type]
        if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
            raise ModbusMapError(f"{self.name} (0x{self.index:04X}.{self.subindex}, {self.type}) takes {lo}..{hi}, "
                                 f"got {value!r}")  # fmt: skip


@dataclass(frozen=True)
class SampleBlock:
    """A contiguous read-only mirror of the objects a master polls together."""

    address: int
    entries: tuple[RegisterEntry, ...]

    @property
    def count(self) -> int:
        return sum(e.count for e in self.entries)


@dataclass(frozen=True)
class RegisterMap:
    """An immutable, validated register map."""

    entries: tuple[RegisterEntry, ...]
    word_order: WordOrder = "high_first"
    sample: SampleBlock | None = None
    source: str = "<code>"
    _by_name: dict[str, RegisterEntry] = field(init=False, repr=False, compare=False)
    _by_obj: dict[tuple[int, int], RegisterEntry] = field(init=False, repr=False, compare=False)
    _by_address: dict[int, tuple[RegisterEntry, int]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.word_order not in ("high_first", "low_first"):
            raise ModbusMapError(f"{self.source}: word_order must be 'high_first' or 'low_first', "
                                 f"got {self.word_order!r}")  # fmt: skip
        by_name: dict[str, RegisterEntry] = {}
        by_obj: dict[tuple[int, int], RegisterEntry] = {}
        by_address: dict[int, tuple[RegisterEntry, int]] = {}
        mirrors = self.sample.entries if self.sample is not None else ()
        for entry in (*self.entries, *mirrors):
            if entry.name in by_name:
                raise ModbusMapError(f"{self.source}: register name {entry.name!r} is defined twice")
            by_name[entry.name] = entry
            if entry not in mirrors:
                if entry.obj in by_obj:
                    raise ModbusMapError(f"{self.source}: object 0x{entry.index:04X}.{entry.subindex} is mapped "
                                         f"twice ({by_obj[entry.obj].name}, {entry.name})")  # fmt: skip
                by_obj[entry.obj] = entry
            for offset in range(entry.count):
                address = entry.address + offset
                if address > 0xFFFF:
                    raise ModbusMapError(f"{self.source}: {entry.name} runs past register 0xFFFF")
                if address in by_address:
                    raise ModbusMapError(f"{self.source}: {entry.name} overlaps {by_address[address][0].name} "
                                         f"at register 0x{address:04X}")  # fmt: skip
                by_address[address] = (entry, offset)
        object.__setattr__(self, "_by_name", by_name)
        object.__setattr__(self, "_by_obj", by_obj)
        object.__setattr__(self, "_by_address", by_address)

    # -- lookups -----------------------------------------------------------------------------
    def __contains__(self, obj: object) -> bool:
        return obj in self._by_obj

    def entry(self, index: int, subindex: int = 0) -> RegisterEntry:
        """The register of CiA 402 object ``index.subindex``; :class:`ModbusMapError` if unmapped."""
        try:
            return self._by_obj[(index, subindex)]
        except KeyError:
            raise ModbusMapError(f"object 0x{index:04X}.{subindex} is not in the register map {self.source}") from None

    def by_name(self, name: str) -> RegisterEntry:
        try:
            return self._by_name[name]
        except KeyError:
            raise ModbusMapError(f"no register named {name!r} in {self.source}") from None

    def covering(self, address: int, count: int) -> list[RegisterEntry]:
        """The entries that exactly tile registers ``address .. address + count - 1``.

        Raises :class:`ModbusMapError` if a register is unmapped or a multi-register object is cut at
        either end of the range (the slave answers both with exception 02).
        """
        out: list[RegisterEntry] = []
        a = address
        end = address + count
        while a < end:
            hit = self._by_address.get(a)
            if hit is None:
                raise ModbusMapError(f"register 0x{a:04X} is not mapped")
            entry, offset = hit
            if offset != 0:
                raise ModbusMapError(f"register 0x{a:04X} is the second half of {entry.name}")
            if a + entry.count > end:
                raise ModbusMapError(f"range ends inside {entry.name} (0x{entry.address:04X}, {entry.count} registers)")
            out.append(entry)
            a += entry.count
        return out

    # -- value <-> registers -----------------------------------------------------------------
    def encode(self, entry: RegisterEntry, value: int) -> tuple[int, ...]:
        """The register values of ``value`` for ``entry`` (range-checked, word order applied)."""
        entry.check_value(value)
        raw = value & (0xFFFF_FFFF if entry.count == 2 else 0xFFFF)
        if entry.count == 1:
            return (raw,)
        high, low = raw >> 16, raw & 0xFFFF
        return (high, low) if self.word_order == "high_first" else (low, high)

    def decode(self, entry: RegisterEntry, registers: Sequence[int]) -> int:
        """The value of ``entry`` from its register values (range-checked)."""
        if len(registers) != entry.count:
            raise ModbusMapError(f"{entry.name} takes {entry.count} registers, got {len(registers)}")
        if entry.count == 1:
            raw, bits = registers[0], 16
        else:
            first, second = registers
            high, low = (first, second) if self.word_order == "high_first" else (second, first)
            raw, bits = (high << 16) | low, 32
        value = raw - (1 << bits) if entry.signed and raw >> (bits - 1) else raw
        entry.check_value(value)
        return value

    def decode_block(self, address: int, registers: Sequence[int]) -> dict[RegisterEntry, int]:
        """Decode a run of registers starting at ``address`` into entry -> value."""
        out: dict[RegisterEntry, int] = {}
        pos = 0
        for entry in self.covering(address, len(registers)):
            out[entry] = self.decode(entry, registers[pos : pos + entry.count])
            pos += entry.count
        return out

    def markdown_table(self) -> str:
        """The map as a Markdown table (used by ``docs/modbus.md``; a test keeps the two in step)."""
        rows = ["| address | registers | object | name | type | access | meaning |",
                "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
        entries = sorted(self.entries, key=lambda e: e.address)
        if self.sample is not None:
            entries += list(self.sample.entries)
        for e in entries:
            rows.append(
                f"| 0x{e.address:04X} | {e.count} | 0x{e.index:04X}.{e.subindex} | {e.name} | {e.type} "
                f"| {e.access} | {e.description} |"
            )
        return "\n".join(rows)

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<dict>") -> RegisterMap:
        known = {"word_order", "register", "sample"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ModbusMapError(f"{source}: unknown top-level key(s) {', '.join(unknown)} (known: {sorted(known)})")
        word_order = data.get("word_order", "high_first")
        registers = data.get("register")
        if not isinstance(registers, list) or not registers:
            raise ModbusMapError(f"{source}: needs a non-empty [[register]] array")
        entries = tuple(_entry_from_dict(r, source, i) for i, r in enumerate(registers))
        sample = None
        if "sample" in data:
            sample = _sample_from_dict(data["sample"], entries, source)
        return cls(entries=entries, word_order=word_order, sample=sample, source=source)


def _int_field(d: Mapping[str, Any], key: str, where: str, lo: int, hi: int, default: int | None = None) -> int:
    value = d.get(key, default)
    if value is None:
        raise ModbusMapError(f"{where}: missing {key!r}")
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ModbusMapError(f"{where}: {key} must be an integer {lo}..{hi}, got {value!r}")
    return value


def _entry_from_dict(d: object, source: str, i: int) -> RegisterEntry:
    where = f"{source}: register #{i + 1}"
    if not isinstance(d, Mapping):
        raise ModbusMapError(f"{where}: must be a table")
    known = {"name", "index", "subindex", "address", "type", "access", "description"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ModbusMapError(f"{where}: unknown key(s) {', '.join(unknown)}")
    name = d.get("name")
    if not isinstance(name, str) or not name:
        raise ModbusMapError(f"{where}: 'name' must be a non-empty string")
    where = f"{source}: register {name!r}"
    type_ = d.get("type")
    if type_ not in _TYPES:
        raise ModbusMapError(f"{where}: type must be one of {', '.join(_TYPES)}, got {type_!r}")
    access = d.get("access", "rw")
    if access not in ("r", "w", "rw"):
        raise ModbusMapError(f"{where}: access must be 'r', 'w' or 'rw', got {access!r}")
    description = d.get("description", "")
    if not isinstance(description, str):
        raise ModbusMapError(f"{where}: description must be a string")
    return RegisterEntry(
        name=name,
        index=_int_field(d, "index", where, 0x1000, 0xFFFF),
        subindex=_int_field(d, "subindex", where, 0, 0xFF, default=0),
        address=_int_field(d, "address", where, 0, 0xFFFF),
        type=type_,
        access=access,
        description=description,
    )


def _sample_from_dict(d: object, entries: Iterable[RegisterEntry], source: str) -> SampleBlock:
    where = f"{source}: [sample]"
    if not isinstance(d, Mapping):
        raise ModbusMapError(f"{where} must be a table")
    unknown = sorted(set(d) - {"address", "objects"})
    if unknown:
        raise ModbusMapError(f"{where}: unknown key(s) {', '.join(unknown)}")
    address = _int_field(d, "address", where, 0, 0xFFFF)
    names = d.get("objects")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ModbusMapError(f"{where}: 'objects' must be a non-empty list of register names")
    by_name = {e.name: e for e in entries}
    mirrors: list[RegisterEntry] = []
    a = address
    for n in names:
        if n not in by_name:
            raise ModbusMapError(f"{where}: no register named {n!r}")
        base = by_name[n]
        if not base.readable:
            raise ModbusMapError(f"{where}: {n!r} is write-only")
        mirrors.append(RegisterEntry(f"sample.{n}", base.index, base.subindex, a, base.type, "r", f"mirror of {n}"))
        a += base.count
    return SampleBlock(address=address, entries=tuple(mirrors))


def load_map(path: str | Path) -> RegisterMap:
    """Load a register map from a TOML file (the whole map; it replaces the default)."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ModbusMapError(f"register map file not found: {p}") from None
    except OSError as exc:
        raise ModbusMapError(f"cannot read register map {p}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ModbusMapError(f"register map {p} is not valid TOML: {exc}") from None
    return RegisterMap.from_dict(data, source=str(p))


_default: RegisterMap | None = None


def default_map() -> RegisterMap:
    """The packaged default map (``drivers/servo/modbus_map.toml``)."""
    global _default
    if _default is None:
        _default = load_map(DEFAULT_MAP_PATH)
    return _default
