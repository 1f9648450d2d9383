"""CiA 402 (drive profile) and the CiA 301 codes it uses: pure definitions, no I/O.

Shared by the CANopen backend, the Modbus RTU backend (which lays the same objects out as
holding registers) and the simulated drive, so that there is one state machine and one set of
decoders in the project.

Contents:

* object indices (:data:`OBJECTS`, with data type, access and PDO mappability),
* controlword commands and bits, statusword bits, :class:`State` and :func:`decode_state`,
* the drive-side transition function :func:`transition` (used by the simulator) and the
  master-side :func:`next_enable_command` (the controlword that moves a drive one step towards
  *Operation enabled*),
* modes of operation, homing status decoding,
* EMCY / error-code (0x603F) decoding, error-register bits, SDO abort codes.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from drivers.errors import DriverError

# --------------------------------------------------------------------------------------------
# Object dictionary: indices of the objects this project uses
# --------------------------------------------------------------------------------------------

DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
DEVICE_NAME = 0x1008
HARDWARE_VERSION = 0x1009
SOFTWARE_VERSION = 0x100A
COB_ID_SYNC = 0x1005
COMM_CYCLE_PERIOD = 0x1006
HIGH_RES_TIMESTAMP = 0x1013
COB_ID_EMCY = 0x1014
CONSUMER_HEARTBEAT_TIME = 0x1016
PRODUCER_HEARTBEAT_TIME = 0x1017
IDENTITY = 0x1018
SYNC_COUNTER_OVERFLOW = 0x1019
RPDO_COMM = 0x1400  # + n (0..3)
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
USER_NOTE = 0x2000  # manufacturer area: a writable visible string (exercises segmented SDO)

ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_DEMAND = 0x6062
POSITION_ACTUAL_INTERNAL = 0x6063
POSITION_ACTUAL = 0x6064
FOLLOWING_ERROR_WINDOW = 0x6065
FOLLOWING_ERROR_TIMEOUT = 0x6066
POSITION_WINDOW = 0x6067
POSITION_WINDOW_TIME = 0x6068
VELOCITY_ACTUAL = 0x606C
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C
SOFTWARE_POSITION_LIMIT = 0x607D  # sub 1 min, sub 2 max
PROFILE_VELOCITY = 0x6081
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
QUICK_STOP_DECELERATION = 0x6085
HOMING_METHOD = 0x6098
HOMING_SPEEDS = 0x6099  # sub 1 switch search, sub 2 zero search
HOMING_ACCELERATION = 0x609A
FOLLOWING_ERROR_ACTUAL = 0x60F4
TARGET_VELOCITY = 0x60FF
SUPPORTED_DRIVE_MODES = 0x6502

DEVICE_TYPE_SERVO = 0x00020192  # profile 402 (0x192), servo drive (type bits 0x0002)


class CodecError(DriverError, ValueError):
    """A value or frame that does not fit its CANopen encoding."""


class DataType(enum.Enum):
    """CANopen basic data types: (CiA 301 type code, struct format, size in bytes)."""

    BOOLEAN = (0x01, "<B", 1)
    INT8 = (0x02, "<b", 1)
    INT16 = (0x03, "<h", 2)
    INT32 = (0x04, "<i", 4)
    UINT8 = (0x05, "<B", 1)
    UINT16 = (0x06, "<H", 2)
    UINT32 = (0x07, "<I", 4)
    VISIBLE_STRING = (0x09, "", 0)

    @property
    def code(self) -> int:
        return self.value[0]

    @property
    def fmt(self) -> str:
        return self.value[1]

    @property
    def size(self) -> int:
        return self.value[2]

    @property
    def bits(self) -> int:
        return 8 * self.value[2]

    @property
    def is_integer(self) -> bool:
        return self is not DataType.VISIBLE_STRING

    @property
    def signed(self) -> bool:
        return self in (DataType.INT8, DataType.INT16, DataType.INT32)

    @property
    def range(self) -> tuple[int, int]:
        if not self.is_integer:
            raise CodecError(f"{self.name} has no integer range")
        if self is DataType.BOOLEAN:
            return 0, 1
        if self.signed:
            return -(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1
        return 0, (1 << self.bits) - 1

    def encode(self, value: int | bytes | str) -> bytes:
        """Little-endian wire encoding of ``value`` (strings as ASCII)."""
        if self is DataType.VISIBLE_STRING:
            if isinstance(value, str):
                return value.encode("ascii")
            if isinstance(value, bytes):
                return value
            raise CodecError(f"VISIBLE_STRING needs str or bytes, got {type(value).__name__}")
        if not isinstance(value, int):
            raise CodecError(f"{self.name} needs an int, got {type(value).__name__}")
        try:
            return struct.pack(self.fmt, value)
        except struct.error:
            raise CodecError(f"{value} does not fit a {self.name}") from None

    def decode(self, data: bytes) -> int:
        """Decode a little-endian integer of this type (``data`` must have the exact size)."""
        if not self.is_integer:
            raise CodecError(f"{self.name} is not an integer type")
        try:
            value: int = struct.unpack(self.fmt, data)[0]
        except struct.error:
            raise CodecError(f"{self.name} needs {self.size} bytes, got {len(data)}") from None
        return value


class Access(enum.Enum):
    RO = "ro"
    WO = "wo"
    RW = "rw"
    CONST = "const"

    @property
    def readable(self) -> bool:
        return self is not Access.WO

    @property
    def writable(self) -> bool:
        return self in (Access.RW, Access.WO)


@dataclass(frozen=True, slots=True)
class ObjectSpec:
    """One object-dictionary entry (index, sub-index) as this project defines it."""

    index: int
    subindex: int
    name: str
    dtype: DataType
    access: Access
    pdo: bool = False  # may be mapped into a PDO
    default: int | str = 0


def _objects() -> dict[tuple[int, int], ObjectSpec]:
    u8, u16, u32, i8, i16, i32 = (
        DataType.UINT8,
        DataType.UINT16,
        DataType.UINT32,
        DataType.INT8,
        DataType.INT16,
        DataType.INT32,
    )
    s = DataType.VISIBLE_STRING
    ro, rw, const = Access.RO, Access.RW, Access.CONST
    specs = [
        ObjectSpec(DEVICE_TYPE, 0, "device type", u32, const, default=DEVICE_TYPE_SERVO),
        ObjectSpec(ERROR_REGISTER, 0, "error register", u8, ro, pdo=True),
        ObjectSpec(COB_ID_SYNC, 0, "COB-ID SYNC", u32, rw, default=0x80),
        ObjectSpec(COMM_CYCLE_PERIOD, 0, "communication cycle period (us)", u32, rw),
        ObjectSpec(DEVICE_NAME, 0, "manufacturer device name", s, const, default="LRMS simulated CiA 402 drive"),
        ObjectSpec(HARDWARE_VERSION, 0, "manufacturer hardware version", s, const, default="sim-1"),
        ObjectSpec(SOFTWARE_VERSION, 0, "manufacturer software version", s, const, default="lrms-0.1"),
        ObjectSpec(HIGH_RES_TIMESTAMP, 0, "high resolution time stamp (us)", u32, rw, pdo=True),
        ObjectSpec(COB_ID_EMCY, 0, "COB-ID EMCY", u32, rw, default=0x80),  # + node id at run time
        ObjectSpec(CONSUMER_HEARTBEAT_TIME, 0, "consumer heartbeat time: number of entries", u8, ro, default=1),
        ObjectSpec(CONSUMER_HEARTBEAT_TIME, 1, "consumer heartbeat time 1", u32, rw),
        ObjectSpec(PRODUCER_HEARTBEAT_TIME, 0, "producer heartbeat time (ms)", u16, rw),
        ObjectSpec(IDENTITY, 0, "identity: number of entries", u8, const, default=4),
        ObjectSpec(IDENTITY, 1, "vendor id", u32, ro, default=0x00000000),
        ObjectSpec(IDENTITY, 2, "product code", u32, ro, default=0x4C524D53),  # "LRMS"
        ObjectSpec(IDENTITY, 3, "revision number", u32, ro, default=0x00010000),
        ObjectSpec(IDENTITY, 4, "serial number", u32, ro, default=1),
        ObjectSpec(SYNC_COUNTER_OVERFLOW, 0, "synchronous counter overflow value", u8, rw),
        ObjectSpec(USER_NOTE, 0, "user note", s, rw, default=""),
        ObjectSpec(ERROR_CODE, 0, "error code", u16, ro, pdo=True),
        ObjectSpec(CONTROLWORD, 0, "controlword", u16, rw, pdo=True),
        ObjectSpec(STATUSWORD, 0, "statusword", u16, ro, pdo=True),
        ObjectSpec(QUICK_STOP_OPTION, 0, "quick stop option code", i16, rw, default=2),
        ObjectSpec(MODES_OF_OPERATION, 0, "modes of operation", i8, rw, pdo=True),
        ObjectSpec(MODES_OF_OPERATION_DISPLAY, 0, "modes of operation display", i8, ro, pdo=True),
        ObjectSpec(POSITION_DEMAND, 0, "position demand value", i32, ro, pdo=True),
        ObjectSpec(POSITION_ACTUAL_INTERNAL, 0, "position actual internal value", i32, ro, pdo=True),
        ObjectSpec(POSITION_ACTUAL, 0, "position actual value", i32, ro, pdo=True),
        ObjectSpec(FOLLOWING_ERROR_WINDOW, 0, "following error window", u32, rw, default=2000),
        ObjectSpec(FOLLOWING_ERROR_TIMEOUT, 0, "following error time out (ms)", u16, rw, default=20),
        ObjectSpec(POSITION_WINDOW, 0, "position window", u32, rw, default=20),
        ObjectSpec(POSITION_WINDOW_TIME, 0, "position window time (ms)", u16, rw, default=5),
        ObjectSpec(VELOCITY_ACTUAL, 0, "velocity actual value", i32, ro, pdo=True),
        ObjectSpec(TARGET_POSITION, 0, "target position", i32, rw, pdo=True),
        ObjectSpec(HOME_OFFSET, 0, "home offset", i32, rw),
        ObjectSpec(SOFTWARE_POSITION_LIMIT, 0, "software position limit: number of entries", u8, const, default=2),
        ObjectSpec(SOFTWARE_POSITION_LIMIT, 1, "min position limit", i32, rw, default=-(1 << 31)),
        ObjectSpec(SOFTWARE_POSITION_LIMIT, 2, "max position limit", i32, rw, default=(1 << 31) - 1),
        ObjectSpec(PROFILE_VELOCITY, 0, "profile velocity", u32, rw, pdo=True, default=100_000),
        ObjectSpec(PROFILE_ACCELERATION, 0, "profile acceleration", u32, rw, pdo=True, default=1_000_000),
        ObjectSpec(PROFILE_DECELERATION, 0, "profile deceleration", u32, rw, pdo=True, default=1_000_000),
        ObjectSpec(QUICK_STOP_DECELERATION, 0, "quick stop deceleration", u32, rw, default=4_000_000),
        ObjectSpec(HOMING_METHOD, 0, "homing method", i8, rw, default=37),
        ObjectSpec(HOMING_SPEEDS, 0, "homing speeds: number of entries", u8, const, default=2),
        ObjectSpec(HOMING_SPEEDS, 1, "speed during search for switch", u32, rw, default=20_000),
        ObjectSpec(HOMING_SPEEDS, 2, "speed during search for zero", u32, rw, default=5_000),
        ObjectSpec(HOMING_ACCELERATION, 0, "homing acceleration", u32, rw, default=500_000),
        ObjectSpec(FOLLOWING_ERROR_ACTUAL, 0, "following error actual value", i32, ro, pdo=True),
        ObjectSpec(TARGET_VELOCITY, 0, "target velocity", i32, rw, pdo=True),
        ObjectSpec(SUPPORTED_DRIVE_MODES, 0, "supported drive modes", u32, const, default=0b100101),
    ]
    for n in range(4):
        specs += [
            ObjectSpec(RPDO_COMM + n, 0, f"RPDO{n + 1} comm: highest sub-index", u8, const, default=5),
            ObjectSpec(RPDO_COMM + n, 1, f"RPDO{n + 1} COB-ID", u32, rw),
            ObjectSpec(RPDO_COMM + n, 2, f"RPDO{n + 1} transmission type", u8, rw, default=255),
            ObjectSpec(RPDO_MAP + n, 0, f"RPDO{n + 1} mapping: number of entries", u8, rw),
            ObjectSpec(TPDO_COMM + n, 0, f"TPDO{n + 1} comm: highest sub-index", u8, const, default=6),
            ObjectSpec(TPDO_COMM + n, 1, f"TPDO{n + 1} COB-ID", u32, rw),
            ObjectSpec(TPDO_COMM + n, 2, f"TPDO{n + 1} transmission type", u8, rw, default=1),
            ObjectSpec(TPDO_COMM + n, 3, f"TPDO{n + 1} inhibit time (100 us)", u16, rw),
            ObjectSpec(TPDO_COMM + n, 5, f"TPDO{n + 1} event timer (ms)", u16, rw),
            ObjectSpec(TPDO_COMM + n, 6, f"TPDO{n + 1} SYNC start value", u8, rw),
            ObjectSpec(TPDO_MAP + n, 0, f"TPDO{n + 1} mapping: number of entries", u8, rw),
        ]
        for k in range(1, 9):
            specs.append(ObjectSpec(RPDO_MAP + n, k, f"RPDO{n + 1} mapped object {k}", u32, rw))
            specs.append(ObjectSpec(TPDO_MAP + n, k, f"TPDO{n + 1} mapped object {k}", u32, rw))
    return {(o.index, o.subindex): o for o in specs}


#: Every object the project's drives carry, keyed by (index, sub-index).
OBJECTS: dict[tuple[int, int], ObjectSpec] = _objects()


def object_spec(index: int, subindex: int = 0) -> ObjectSpec:
    """The :class:`ObjectSpec` of (index, sub-index); ``KeyError`` if the project has no such object."""
    return OBJECTS[(index, subindex)]


def pdo_map_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry: index << 16 | sub-index << 8 | bit length (0x60640020 = position actual)."""
    return (index << 16) | (subindex << 8) | bits


def split_pdo_map_entry(entry: int) -> tuple[int, int, int]:
    return (entry >> 16) & 0xFFFF, (entry >> 8) & 0xFF, entry & 0xFF


#: A PDO's mapping: (index, sub-index, bits) per mapped object, in frame order.
PdoMapping = tuple[tuple[int, int, int], ...]

#: The sample TPDOs a master maps when the drive has no time stamp: TPDO1 = statusword + position
#: actual, TPDO2 = velocity actual + following error.
SAMPLE_TPDOS_PLAIN: tuple[PdoMapping, PdoMapping] = (
    ((STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32)),
    ((VELOCITY_ACTUAL, 0, 32), (FOLLOWING_ERROR_ACTUAL, 0, 32)),
)
#: ... and when it has 0x1013: TPDO1 = position actual + the drive's time stamp of the same latch
#: (64 bits, full), TPDO2 = statusword + velocity actual.
SAMPLE_TPDOS_STAMPED: tuple[PdoMapping, PdoMapping] = (
    ((POSITION_ACTUAL, 0, 32), (HIGH_RES_TIMESTAMP, 0, 32)),
    ((STATUSWORD, 0, 16), (VELOCITY_ACTUAL, 0, 32)),
)


def unpack_pdo(mapping: PdoMapping, data: bytes) -> dict[int, int]:
    """The values of a received PDO by object index (sub-index 0 objects, whole bytes only).

    :class:`CodecError` if the frame is shorter than the mapping or an entry is not a whole
    integer object of the project (the mapping is the master's own, so that is a programming error)."""
    out: dict[int, int] = {}
    offset = 0
    for index, subindex, bits in mapping:
        spec = OBJECTS.get((index, subindex))
        if spec is None or not spec.dtype.is_integer or bits != spec.dtype.bits:
            raise CodecError(f"0x{index:04X}:{subindex:02X} ({bits} bits) is not a mappable integer object")
        size = bits // 8
        if len(data) < offset + size:
            raise CodecError(f"PDO of {len(data)} bytes is shorter than its mapping ({offset + size}+ bytes)")
        out[index] = spec.dtype.decode(bytes(data[offset : offset + size]))
        offset += size
    return out


# --------------------------------------------------------------------------------------------
# Controlword
# --------------------------------------------------------------------------------------------

CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low
CW_ENABLE_OPERATION = 1 << 3
CW_NEW_SET_POINT = 1 << 4  # PP; "homing operation start" in HM
CW_CHANGE_SET_IMMEDIATELY = 1 << 5  # PP
CW_RELATIVE = 1 << 6  # PP
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8
CW_CHANGE_ON_SET_POINT = 1 << 9  # PP

CMD_SHUTDOWN = 0x0006
CMD_SWITCH_ON = 0x0007
CMD_DISABLE_VOLTAGE = 0x0000
CMD_QUICK_STOP = 0x0002
CMD_DISABLE_OPERATION = 0x0007
CMD_ENABLE_OPERATION = 0x000F
CMD_FAULT_RESET = 0x0080


class Command(enum.Enum):
    """Device-control command encoded in controlword bits 0-3 and 7."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"  # also "disable operation" from Operation enabled
    ENABLE_OPERATION = "enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    FAULT_RESET = "fault reset"  # bit 7 set; acts on the rising edge only


def decode_command(controlword: int) -> Command:
    """The device-control command of ``controlword`` (CiA 402 table; bits 4-6, 8-15 ignored)."""
    if controlword & CW_FAULT_RESET:
        return Command.FAULT_RESET
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not controlword & CW_SWITCH_ON:
        return Command.SHUTDOWN
    if controlword & CW_ENABLE_OPERATION:
        return Command.ENABLE_OPERATION
    return Command.SWITCH_ON


# --------------------------------------------------------------------------------------------
# Statusword and states
# --------------------------------------------------------------------------------------------

SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # 0 = quick stop active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_SET_POINT_ACK = 1 << 12  # PP; "speed = 0" in PV; "homing attained" in HM
SW_FOLLOWING_ERROR = 1 << 13  # PP; "max slippage" in PV; "homing error" in HM
SW_SPEED_ZERO = SW_SET_POINT_ACK
SW_HOMING_ATTAINED = SW_SET_POINT_ACK
SW_HOMING_ERROR = SW_FOLLOWING_ERROR


class State(enum.Enum):
    """CiA 402 power drive system states, with the statusword (mask, value) that identifies each."""

    NOT_READY_TO_SWITCH_ON = ("Not ready to switch on", 0x4F, 0x00)
    SWITCH_ON_DISABLED = ("Switch on disabled", 0x4F, 0x40)
    READY_TO_SWITCH_ON = ("Ready to switch on", 0x6F, 0x21)
    SWITCHED_ON = ("Switched on", 0x6F, 0x23)
    OPERATION_ENABLED = ("Operation enabled", 0x6F, 0x27)
    QUICK_STOP_ACTIVE = ("Quick stop active", 0x6F, 0x07)
    FAULT_REACTION_ACTIVE = ("Fault reaction active", 0x4F, 0x0F)
    FAULT = ("Fault", 0x4F, 0x08)

    @property
    def label(self) -> str:
        return self.value[0]

    @property
    def mask(self) -> int:
        return self.value[1]

    @property
    def bits(self) -> int:
        """Statusword bits 0-6 a drive reports in this state (bit 4 "voltage enabled" included
        where the power stage is on, bit 5 "quick stop" = 1 where no quick stop is active)."""
        return _STATE_BITS[self]


_STATE_BITS = {
    State.NOT_READY_TO_SWITCH_ON: 0x00,
    State.SWITCH_ON_DISABLED: 0x40,
    State.READY_TO_SWITCH_ON: 0x31,
    State.SWITCHED_ON: 0x33,
    State.OPERATION_ENABLED: 0x37,
    State.QUICK_STOP_ACTIVE: 0x17,
    State.FAULT_REACTION_ACTIVE: 0x1F,
    State.FAULT: 0x08,
}


class StatuswordError(DriverError, ValueError):
    """A statusword matches no CiA 402 state."""


def decode_state(statusword: int) -> State:
    """The CiA 402 state of ``statusword``, decoded with the masks (never the whole word)."""
    for state in State:
        if statusword & state.mask == state.value[2]:
            return state
    raise StatuswordError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


def describe_statusword(statusword: int) -> str:
    """Human-readable summary: state plus the set flag bits."""
    try:
        text = decode_state(statusword).label
    except StatuswordError:
        text = "invalid state"
    flags = [
        name
        for bit, name in (
            (SW_WARNING, "warning"),
            (SW_REMOTE, "remote"),
            (SW_TARGET_REACHED, "target reached"),
            (SW_INTERNAL_LIMIT, "internal limit"),
            (SW_SET_POINT_ACK, "bit12"),
            (SW_FOLLOWING_ERROR, "bit13"),
        )
        if statusword & bit
    ]
    return f"{text} (0x{statusword:04X}{', ' + ', '.join(flags) if flags else ''})"


def transition(state: State, command: Command, *, quick_stop_option: int = 2) -> State:
    """Drive-side state machine: the state after ``command`` arrives in ``state``.

    Automatic transitions (0 and 1 after power-on, 13/14 through *Fault reaction active*, and the
    end of a quick-stop ramp) are the drive's own business and not covered here. A fault-reset
    command is passed only on the rising edge of bit 7. Commands that are not valid in a state
    leave it unchanged, as drives do. ``quick_stop_option`` (0x605A) 5-8 keep the drive in
    *Quick stop active* after the ramp; 0-4 end in *Switch on disabled* (handled by the drive
    when the ramp ends), so the transition here is always into *Quick stop active*.
    """
    del quick_stop_option  # the post-ramp behaviour is the drive's, documented above
    s, c = State, Command
    if state is s.FAULT:
        return s.SWITCH_ON_DISABLED if command is c.FAULT_RESET else state
    if state in (s.FAULT_REACTION_ACTIVE, s.NOT_READY_TO_SWITCH_ON):
        return state
    if command is c.FAULT_RESET:  # rising edge outside Fault: no effect on the state
        return state
    if command is c.DISABLE_VOLTAGE:
        return s.SWITCH_ON_DISABLED  # 7, 9, 10, 12
    if state is s.SWITCH_ON_DISABLED:
        return s.READY_TO_SWITCH_ON if command is c.SHUTDOWN else state  # 2
    if state is s.READY_TO_SWITCH_ON:
        if command is c.QUICK_STOP:
            return s.SWITCH_ON_DISABLED  # 7
        if command in (c.SWITCH_ON, c.ENABLE_OPERATION):
            return s.SWITCHED_ON  # 3 (3+4 in one go is allowed by many drives, not by us)
        return state
    if state is s.SWITCHED_ON:
        if command is c.QUICK_STOP:
            return s.SWITCH_ON_DISABLED  # 10
        if command is c.SHUTDOWN:
            return s.READY_TO_SWITCH_ON  # 6
        if command is c.ENABLE_OPERATION:
            return s.OPERATION_ENABLED  # 4
        return state
    if state is s.OPERATION_ENABLED:
        if command is c.QUICK_STOP:
            return s.QUICK_STOP_ACTIVE  # 11
        if command is c.SHUTDOWN:
            return s.READY_TO_SWITCH_ON  # 8
        if command is c.SWITCH_ON:
            return s.SWITCHED_ON  # 5
        return state
    if state is s.QUICK_STOP_ACTIVE:
        if command is c.ENABLE_OPERATION:
            return s.OPERATION_ENABLED  # 16
        return state
    raise AssertionError(f"unhandled state {state}")  # pragma: no cover


def next_enable_command(state: State) -> int | None:
    """Master side: the controlword that moves a drive in ``state`` one step towards
    *Operation enabled*; ``None`` when already there. In *Fault* it is the fault-reset word
    (the caller must have written a word with bit 7 clear before, for the rising edge)."""
    return {
        State.OPERATION_ENABLED: None,
        State.SWITCHED_ON: CMD_ENABLE_OPERATION,
        State.READY_TO_SWITCH_ON: CMD_SWITCH_ON,
        State.SWITCH_ON_DISABLED: CMD_SHUTDOWN,
        State.NOT_READY_TO_SWITCH_ON: CMD_SHUTDOWN,
        State.QUICK_STOP_ACTIVE: CMD_ENABLE_OPERATION,
        State.FAULT: CMD_FAULT_RESET,
        State.FAULT_REACTION_ACTIVE: CMD_FAULT_RESET,
    }[state]


# --------------------------------------------------------------------------------------------
# Modes of operation
# --------------------------------------------------------------------------------------------


class Mode(enum.IntEnum):
    NO_MODE = 0
    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


#: Bit of each mode in 0x6502 "supported drive modes".
SUPPORTED_MODE_BIT = {
    Mode.PROFILE_POSITION: 0,
    Mode.VELOCITY: 1,
    Mode.PROFILE_VELOCITY: 2,
    Mode.PROFILE_TORQUE: 3,
    Mode.INTERPOLATED_POSITION: 4,
    Mode.HOMING: 5,
    Mode.CYCLIC_SYNC_POSITION: 7,
    Mode.CYCLIC_SYNC_VELOCITY: 8,
    Mode.CYCLIC_SYNC_TORQUE: 9,
}


def mode_supported(supported_drive_modes: int, mode: int) -> bool:
    try:
        bit = SUPPORTED_MODE_BIT[Mode(mode)]
    except (ValueError, KeyError):
        return False
    return bool(supported_drive_modes >> bit & 1)


class HomingStatus(enum.Enum):
    IN_PROGRESS = "homing in progress"
    INTERRUPTED = "homing interrupted or not started"
    ATTAINED_NOT_REACHED = "homing attained, target not reached"
    COMPLETED = "homing completed"
    ERROR_MOVING = "homing error, motor still moving"
    ERROR_STOPPED = "homing error, motor stopped"


def decode_homing_status(statusword: int) -> HomingStatus:
    """Homing-mode status from statusword bits 13 / 12 / 10 (CiA 402 table)."""
    key = (
        bool(statusword & SW_HOMING_ERROR),
        bool(statusword & SW_HOMING_ATTAINED),
        bool(statusword & SW_TARGET_REACHED),
    )
    table = {
        (False, False, False): HomingStatus.IN_PROGRESS,
        (False, False, True): HomingStatus.INTERRUPTED,
        (False, True, False): HomingStatus.ATTAINED_NOT_REACHED,
        (False, True, True): HomingStatus.COMPLETED,
        (True, False, False): HomingStatus.ERROR_MOVING,
        (True, False, True): HomingStatus.ERROR_STOPPED,
    }
    # (True, True, x) is reserved in the standard: report it as an error with the motor stopped
    return table.get(key, HomingStatus.ERROR_STOPPED)


# --------------------------------------------------------------------------------------------
# Error codes (0x603F, EMCY), error register (0x1001)
# --------------------------------------------------------------------------------------------

ERR_NONE = 0x0000
ERR_GENERIC = 0x1000
ERR_OVER_CURRENT = 0x2310  # continuous over-current (device output side)
ERR_SHORT_CIRCUIT = 0x2320
ERR_DC_LINK_OVER_VOLTAGE = 0x3210
ERR_DC_LINK_UNDER_VOLTAGE = 0x3220
ERR_OVER_TEMPERATURE = 0x4210
ERR_SOFTWARE = 0x6100
ERR_ENCODER = 0x7305
ERR_CAN_OVERRUN = 0x8110
ERR_CAN_PASSIVE = 0x8120
ERR_HEARTBEAT = 0x8130
ERR_BUS_OFF_RECOVERED = 0x8140
ERR_FOLLOWING_ERROR = 0x8611
ERR_POSITION_LIMIT = 0x8612  # software/hardware position limit
ERR_VENDOR = 0xFF00

_ERROR_TEXT_EXACT = {
    ERR_NONE: "no error / error reset",
    ERR_GENERIC: "generic error",
    ERR_OVER_CURRENT: "continuous over-current",
    ERR_SHORT_CIRCUIT: "short circuit / earth leakage",
    ERR_DC_LINK_OVER_VOLTAGE: "DC link over-voltage",
    ERR_DC_LINK_UNDER_VOLTAGE: "DC link under-voltage",
    ERR_OVER_TEMPERATURE: "excess ambient / device temperature",
    ERR_SOFTWARE: "internal software error",
    ERR_ENCODER: "incremental sensor (encoder) fault",
    ERR_CAN_OVERRUN: "CAN overrun (objects lost)",
    ERR_CAN_PASSIVE: "CAN in error passive mode",
    ERR_HEARTBEAT: "life guard / heartbeat error",
    ERR_BUS_OFF_RECOVERED: "recovered from bus off",
    ERR_FOLLOWING_ERROR: "following error",
    ERR_POSITION_LIMIT: "position reference limit",
}

_ERROR_FAMILY = [  # (prefix mask, prefix value, text), most specific first
    (0xFF00, 0x2100, "current, device input side"),
    (0xFF00, 0x2200, "current inside the device"),
    (0xFF00, 0x2300, "current, device output side"),
    (0xF000, 0x2000, "current"),
    (0xFF00, 0x3100, "mains voltage"),
    (0xFF00, 0x3200, "voltage inside the device"),
    (0xF000, 0x3000, "voltage"),
    (0xF000, 0x4000, "temperature"),
    (0xF000, 0x5000, "device hardware"),
    (0xF000, 0x6000, "device software"),
    (0xF000, 0x7000, "additional modules / sensor"),
    (0xFF00, 0x8100, "communication"),
    (0xFF00, 0x8200, "protocol error"),
    (0xFF00, 0x8600, "positioning controller"),
    (0xF000, 0x8000, "monitoring"),
    (0xF000, 0x9000, "external error"),
    (0xFF00, 0xF000, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
]


def describe_error_code(code: int) -> str:
    """Text of a CiA 301 / 402 error code (0x603F, EMCY); unknown codes get their family."""
    if code in _ERROR_TEXT_EXACT:
        return _ERROR_TEXT_EXACT[code]
    for mask, value, text in _ERROR_FAMILY:
        if code & mask == value:
            return f"{text} error 0x{code:04X}"
    return f"unknown error code 0x{code:04X}"


ERROR_REGISTER_BITS = {
    0: "generic",
    1: "current",
    2: "voltage",
    3: "temperature",
    4: "communication",
    5: "device profile specific",
    7: "manufacturer specific",
}


def error_register_for(code: int) -> int:
    """The error-register (0x1001) bits a drive sets for ``code`` (bit 0 for every error)."""
    if code == ERR_NONE:
        return 0
    reg = 0x01
    family = code & 0xF000
    if family == 0x2000:
        reg |= 0x02
    elif family == 0x3000:
        reg |= 0x04
    elif family == 0x4000:
        reg |= 0x08
    elif code & 0xFF00 in (0x8100, 0x8200):  # communication, protocol
        reg |= 0x10
    elif code & 0xFF00 == 0x8600:
        reg |= 0x20
    elif code & 0xFF00 == 0xFF00:
        reg |= 0x80
    return reg


def describe_error_register(register: int) -> list[str]:
    return [text for bit, text in ERROR_REGISTER_BITS.items() if register >> bit & 1]


@dataclass(frozen=True, slots=True)
class Emcy:
    """A decoded EMCY frame (0x80 + node): error code, error register and 5 vendor bytes."""

    code: int
    register: int
    vendor: bytes = b"\x00" * 5

    @classmethod
    def decode(cls, data: bytes) -> Emcy:
        if len(data) != 8:
            raise CodecError(f"EMCY frame must carry 8 bytes, got {len(data)}")
        code, register = struct.unpack_from("<HB", data)
        return cls(code=code, register=register, vendor=bytes(data[3:8]))

    def encode(self) -> bytes:
        if len(self.vendor) != 5:
            raise CodecError("EMCY vendor field is 5 bytes")
        return struct.pack("<HB", self.code, self.register) + self.vendor

    @property
    def is_reset(self) -> bool:
        return self.code == ERR_NONE

    @property
    def reason(self) -> str:
        return describe_error_code(self.code)

    def __str__(self) -> str:
        reg = ", ".join(describe_error_register(self.register)) or "none"
        return f"EMCY 0x{self.code:04X} {self.reason} (error register 0x{self.register:02X}: {reg})"


# --------------------------------------------------------------------------------------------
# SDO abort codes (CiA 301)
# --------------------------------------------------------------------------------------------

ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_OUT_OF_MEMORY = 0x05040005
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
ABORT_HARDWARE = 0x06060000
ABORT_TYPE_MISMATCH = 0x06070010
ABORT_LENGTH_TOO_HIGH = 0x06070012
ABORT_LENGTH_TOO_LOW = 0x06070013
ABORT_NO_SUBINDEX = 0x06090011
ABORT_INVALID_VALUE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_MAX_LESS_THAN_MIN = 0x06090036
ABORT_RESOURCE = 0x060A0023
ABORT_GENERAL = 0x08000000
ABORT_STORE = 0x08000020
ABORT_LOCAL_CONTROL = 0x08000021
ABORT_DEVICE_STATE = 0x08000022
ABORT_NO_DICTIONARY = 0x08000023
ABORT_NO_DATA = 0x08000024

SDO_ABORT_TEXT = {
    ABORT_TOGGLE: "toggle bit not alternated",
    ABORT_TIMEOUT: "SDO protocol timed out",
    ABORT_COMMAND: "client/server command specifier not valid or unknown",
    0x05040002: "invalid block size",
    0x05040003: "invalid sequence number",
    0x05040004: "CRC error",
    ABORT_OUT_OF_MEMORY: "out of memory",
    ABORT_UNSUPPORTED_ACCESS: "unsupported access to an object",
    ABORT_WRITE_ONLY: "attempt to read a write-only object",
    ABORT_READ_ONLY: "attempt to write a read-only object",
    ABORT_NO_OBJECT: "object does not exist in the object dictionary",
    ABORT_NOT_MAPPABLE: "object cannot be mapped to the PDO",
    ABORT_PDO_LENGTH: "number and length of mapped objects would exceed PDO length",
    ABORT_PARAMETER_INCOMPATIBLE: "general parameter incompatibility",
    0x06040047: "general internal incompatibility in the device",
    ABORT_HARDWARE: "access failed due to a hardware error",
    ABORT_TYPE_MISMATCH: "data type does not match, length of service parameter does not match",
    ABORT_LENGTH_TOO_HIGH: "data type does not match, length of service parameter too high",
    ABORT_LENGTH_TOO_LOW: "data type does not match, length of service parameter too low",
    ABORT_NO_SUBINDEX: "sub-index does not exist",
    ABORT_INVALID_VALUE: "invalid value for parameter (value range exceeded)",
    ABORT_VALUE_TOO_HIGH: "value of parameter written too high",
    ABORT_VALUE_TOO_LOW: "value of parameter written too low",
    ABORT_MAX_LESS_THAN_MIN: "maximum value is less than minimum value",
    ABORT_RESOURCE: "resource not available: SDO connection",
    ABORT_GENERAL: "general error",
    ABORT_STORE: "data cannot be transferred or stored to the application",
    ABORT_LOCAL_CONTROL: "data cannot be transferred or stored because of local control",
    ABORT_DEVICE_STATE: "data cannot be transferred or stored because of the present device state",
    ABORT_NO_DICTIONARY: "object dictionary dynamic generation failed or no dictionary present",
    ABORT_NO_DATA: "no data available",
}


def describe_sdo_abort(code: int) -> str:
    return SDO_ABORT_TEXT.get(code, f"unknown SDO abort code 0x{code:08X}")
