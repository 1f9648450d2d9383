"""The simulated CiA 402 servo drive: object dictionary, state machine and motion, no protocol.

Both protocol front ends (the CANopen node in :mod:`sim.drive.can_node` and the Modbus RTU
server) sit on one :class:`SimDrive` and see the same objects through
``read(index, subindex) -> int`` / ``write(index, subindex, value)``. Everything is guarded by
one re-entrant lock (``drive.lock``), so the front ends may call from their own threads.

Physics, advanced lazily to the present instant of ``clock`` on every access (and by the front
ends' periodic ticks), in sub-steps of at most :attr:`SimDrive.max_step_s`:

* the trajectory generator (position demand 0x6062) runs a trapezoidal profile: velocity is the
  least of the accelerated velocity, the cruise velocity and the stopping-curve velocity
  ``sqrt(2 * deceleration * remaining distance)``, so moves land exactly on target;
* the axis (position actual 0x6064) follows the demand as a first-order servo loop with time
  constant :attr:`SimDrive.servo_tau_s`; following error 0x60F4 = demand - actual;
* a following error beyond 0x6065 for longer than 0x6066 ms is fault 0x8611; software limits
  0x607D clamp targets (statusword bit 11, "internal limit active") and stop jogs at the limit;
* injectable faults: ``following_error`` (the axis stalls: it stops following the demand, so
  the next move trips the following-error monitor), ``over_current`` (fault 0x2310 at once),
  ``heartbeat_loss`` (the CAN front end stops producing heartbeats; :attr:`silent`).

Units: position in encoder counts, velocity counts/s, accelerations counts/s², as on the drive.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from drivers.servo import cia402
from drivers.servo.cia402 import Command, Mode, ObjectSpec, State

Clock = Callable[[], float]
EmcyListener = Callable[[int, int], None]  # (error code, error register)

FAULT_KINDS = ("following_error", "over_current", "heartbeat_loss")

#: Homing methods the simulated drive accepts: 35/37 "the present position is home"; 19/20 a home
#: switch active above :attr:`SimDrive.home_switch_position`, 21/22 one active below it (the
#: simulated switch has one edge, so 19 = 20 and 21 = 22 here).
SUPPORTED_HOMING_METHODS = (19, 20, 21, 22, 35, 37)

_MAPPABLE_BITS = 64  # classic CAN: 8 bytes per PDO


class ObjectAccessError(Exception):
    """An object access the drive refuses; ``abort_code`` is the CiA 301 SDO abort code.

    The CANopen front end answers with an SDO abort carrying it, the Modbus front end maps it to
    an exception response.
    """

    def __init__(self, index: int, subindex: int, abort_code: int) -> None:
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code
        super().__init__(f"0x{index:04X}:{subindex:02X}: 0x{abort_code:08X} {cia402.describe_sdo_abort(abort_code)}")


@dataclass
class _Profile:
    velocity: float
    acceleration: float
    deceleration: float


class SimDrive:
    """A simulated CiA 402 position servo (see the module docstring)."""

    max_step_s = 0.0005
    servo_tau_s = 0.002
    velocity_window = 100.0  # counts/s, "target velocity reached" (PV bit 10) and "speed = 0" (PV bit 12)
    home_switch_position = 5_000.0  # raw axis counts where the simulated home switch changes state

    def __init__(self, node_id: int = 1, *, clock: Clock = time.monotonic, position: int = 0) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id must be 1..127, got {node_id}")
        self.node_id = node_id
        self.clock = clock
        self.lock = threading.RLock()
        self._store: dict[tuple[int, int], int | str] = {k: s.default for k, s in cia402.OBJECTS.items()}
        self._defaults_for_node()
        self._t = clock()
        self._t0 = self._t
        self._emcy_listeners: list[EmcyListener] = []
        # motion state (counts, counts/s)
        self._demand = float(position)
        self._demand_vel = 0.0
        self._landing = False
        self._actual = float(position)
        self._actual_vel = 0.0
        self._home_shift = 0.0  # added to the encoder reading after homing
        # 402 state
        self._state = State.SWITCH_ON_DISABLED
        self._cw = 0
        self._mode = Mode.NO_MODE
        self._target: float | None = None  # active PP target (counts)
        self._pending: tuple[float, _Profile] | None = None
        self._profile = _Profile(1.0, 1.0, 1.0)
        self._set_point_ack = False
        self._target_reached = True
        self._in_window_since: float | None = None
        self._internal_limit = False
        self._following_error_flag = False
        self._fe_since: float | None = None
        self._homing = "idle"  # idle | running | done | error
        self._homing_phase = "search"  # search | back | stop (switch methods)
        self._homing_dir = 1.0
        self._homing_side = False
        self._error_code = 0
        self._error_register = 0
        # injected conditions
        self.stalled = False
        self.silent = False
        self._frozen = 0

    def _defaults_for_node(self) -> None:
        n = self.node_id
        s = self._store
        s[(cia402.COB_ID_EMCY, 0)] = 0x80 + n
        invalid = 1 << 31
        for k in range(4):
            s[(cia402.TPDO_COMM + k, 1)] = (0x180 + 0x100 * k + n) | (0 if k < 2 else invalid)
            s[(cia402.RPDO_COMM + k, 1)] = (0x200 + 0x100 * k + n) | (0 if k < 2 else invalid)
        e = cia402.pdo_map_entry
        maps = {
            cia402.TPDO_MAP: [e(cia402.STATUSWORD, 0, 16), e(cia402.POSITION_ACTUAL, 0, 32)],
            cia402.TPDO_MAP + 1: [e(cia402.VELOCITY_ACTUAL, 0, 32), e(cia402.FOLLOWING_ERROR_ACTUAL, 0, 32)],
            cia402.RPDO_MAP: [e(cia402.CONTROLWORD, 0, 16)],
            cia402.RPDO_MAP + 1: [e(cia402.TARGET_POSITION, 0, 32), e(cia402.PROFILE_VELOCITY, 0, 32)],
        }
        for index, entries in maps.items():
            s[(index, 0)] = len(entries)
            for sub, entry in enumerate(entries, start=1):
                s[(index, sub)] = entry

    # ------------------------------------------------------------------------------------------
    # object access
    # ------------------------------------------------------------------------------------------
    @staticmethod
    def spec(index: int, subindex: int = 0) -> ObjectSpec:
        """The object's spec, or :class:`ObjectAccessError` (no object / no sub-index)."""
        spec = cia402.OBJECTS.get((index, subindex))
        if spec is None:
            known_index = any(i == index for i, _ in cia402.OBJECTS)
            raise ObjectAccessError(
                index, subindex, cia402.ABORT_NO_SUBINDEX if known_index else cia402.ABORT_NO_OBJECT
            )
        return spec

    def read(self, index: int, subindex: int = 0) -> int:
        """Read an integer object (live values computed at the present instant)."""
        spec = self.spec(index, subindex)
        if not spec.dtype.is_integer:
            raise ObjectAccessError(index, subindex, cia402.ABORT_TYPE_MISMATCH)
        value = self._read(spec)
        assert isinstance(value, int)
        return value

    def read_bytes(self, index: int, subindex: int = 0) -> bytes:
        """Read an object in its CANopen wire encoding (little-endian; strings as ASCII)."""
        spec = self.spec(index, subindex)
        return spec.dtype.encode(self._read(spec))

    def _read(self, spec: ObjectSpec) -> int | str:
        if not spec.access.readable:
            raise ObjectAccessError(spec.index, spec.subindex, cia402.ABORT_WRITE_ONLY)
        with self.lock:
            self.advance()
            live = self._live(spec.index)
            if live is not None:
                return live
            return self._store[(spec.index, spec.subindex)]

    @property
    def stamp_epoch(self) -> float:
        """The drive clock's reading (s) at which its time stamp 0x1013 read 0: the stamp is
        ``(drive time - stamp_epoch)`` in µs, modulo 2**32."""
        return self._t0

    def _live(self, index: int) -> int | None:
        if index == cia402.STATUSWORD:
            return self._statusword()
        if index == cia402.POSITION_ACTUAL or index == cia402.POSITION_ACTUAL_INTERNAL:
            return _i32(self._actual + self._home_shift)
        if index == cia402.POSITION_DEMAND:
            return _i32(self._demand + self._home_shift)
        if index == cia402.VELOCITY_ACTUAL:
            return _i32(self._actual_vel)
        if index == cia402.FOLLOWING_ERROR_ACTUAL:
            return _i32(self._demand - self._actual)
        if index == cia402.MODES_OF_OPERATION_DISPLAY:
            return int(self._mode)
        if index == cia402.ERROR_CODE:
            return self._error_code
        if index == cia402.ERROR_REGISTER:
            return self._error_register
        if index == cia402.CONTROLWORD:
            return self._cw
        if index == cia402.HIGH_RES_TIMESTAMP:
            return round((self._t - self._t0) * 1e6) & 0xFFFFFFFF
        return None

    def write(self, index: int, subindex: int, value: int) -> None:
        """Write an integer object; range, access and meaning are checked as a drive would."""
        spec = self.spec(index, subindex)
        if not spec.dtype.is_integer:
            raise ObjectAccessError(index, subindex, cia402.ABORT_TYPE_MISMATCH)
        if not isinstance(value, int) or isinstance(value, bool):
            raise ObjectAccessError(index, subindex, cia402.ABORT_TYPE_MISMATCH)
        self._write(spec, value)

    def write_bytes(self, index: int, subindex: int, data: bytes) -> None:
        """Write an object from its wire encoding (an SDO download)."""
        spec = self.spec(index, subindex)
        if not spec.dtype.is_integer:
            if not spec.access.writable:
                raise ObjectAccessError(index, subindex, cia402.ABORT_READ_ONLY)
            if len(data) > 255:
                raise ObjectAccessError(index, subindex, cia402.ABORT_LENGTH_TOO_HIGH)
            try:
                text = data.decode("ascii")
            except UnicodeDecodeError:
                raise ObjectAccessError(index, subindex, cia402.ABORT_INVALID_VALUE) from None
            with self.lock:
                self._store[(index, subindex)] = text
            return
        if len(data) > spec.dtype.size:
            raise ObjectAccessError(index, subindex, cia402.ABORT_LENGTH_TOO_HIGH)
        if len(data) < spec.dtype.size:
            raise ObjectAccessError(index, subindex, cia402.ABORT_LENGTH_TOO_LOW)
        self._write(spec, spec.dtype.decode(data))

    def _write(self, spec: ObjectSpec, value: int) -> None:
        index, sub = spec.index, spec.subindex
        if not spec.access.writable:
            raise ObjectAccessError(index, sub, cia402.ABORT_READ_ONLY)
        lo, hi = spec.dtype.range
        if value > hi:
            raise ObjectAccessError(index, sub, cia402.ABORT_VALUE_TOO_HIGH)
        if value < lo:
            raise ObjectAccessError(index, sub, cia402.ABORT_VALUE_TOO_LOW)
        with self.lock:
            self.advance()
            self._check_semantics(spec, value)
            if index == cia402.CONTROLWORD:
                self._on_controlword(value)
                return
            self._store[(index, sub)] = value
            if index == cia402.MODES_OF_OPERATION:
                self._mode = Mode(value)

    def _check_semantics(self, spec: ObjectSpec, value: int) -> None:
        index, sub = spec.index, spec.subindex
        bad = cia402.ABORT_INVALID_VALUE
        if index == cia402.MODES_OF_OPERATION and not cia402.mode_supported(
            int(self._store[(cia402.SUPPORTED_DRIVE_MODES, 0)]), value
        ):
            raise ObjectAccessError(index, sub, bad)
        if index == cia402.HOMING_METHOD and value not in SUPPORTED_HOMING_METHODS:
            raise ObjectAccessError(index, sub, bad)
        if index == cia402.QUICK_STOP_OPTION and not 0 <= value <= 8:
            raise ObjectAccessError(index, sub, bad)
        if index == cia402.SOFTWARE_POSITION_LIMIT:
            lo = value if sub == 1 else int(self._store[(index, 1)])
            hi = value if sub == 2 else int(self._store[(index, 2)])
            if lo > hi:
                raise ObjectAccessError(index, sub, cia402.ABORT_MAX_LESS_THAN_MIN)
        is_map = cia402.TPDO_MAP <= index < cia402.TPDO_MAP + 4 or cia402.RPDO_MAP <= index < cia402.RPDO_MAP + 4
        if is_map and sub >= 1 and value != 0:
            m_index, m_sub, bits = cia402.split_pdo_map_entry(value)
            target = cia402.OBJECTS.get((m_index, m_sub))
            if target is None:
                raise ObjectAccessError(index, sub, cia402.ABORT_NO_OBJECT)
            receive = index < cia402.TPDO_MAP
            access_ok = target.access.writable if receive else target.access.readable
            if not target.pdo or not access_ok or bits != target.dtype.bits:
                raise ObjectAccessError(index, sub, cia402.ABORT_NOT_MAPPABLE)
        if is_map and sub == 0:
            if value > 8:
                raise ObjectAccessError(index, sub, cia402.ABORT_VALUE_TOO_HIGH)
            total = sum(int(self._store[(index, k)]) & 0xFF for k in range(1, value + 1))
            if total > _MAPPABLE_BITS:
                raise ObjectAccessError(index, sub, cia402.ABORT_PDO_LENGTH)

    def pdo_mapping(self, map_index: int) -> list[tuple[int, int, int]]:
        """(index, sub-index, bits) entries of PDO mapping object ``map_index`` (0x1600.., 0x1A00..)."""
        with self.lock:
            n = int(self._store[(map_index, 0)])
            return [cia402.split_pdo_map_entry(int(self._store[(map_index, k)])) for k in range(1, n + 1)]

    def raw(self, index: int, subindex: int = 0) -> int | str:
        """The stored value without access checks or live computation (front-end bookkeeping)."""
        with self.lock:
            return self._store[(index, subindex)]

    # ------------------------------------------------------------------------------------------
    # faults and events
    # ------------------------------------------------------------------------------------------
    def add_emcy_listener(self, listener: EmcyListener) -> None:
        """``listener(code, register)`` is called (under the drive lock) when a fault is raised
        and with code 0 when it is reset. Keep it short; it must not call back into a blocking wait."""
        self._emcy_listeners.append(listener)

    def inject_fault(self, kind: str) -> None:
        """Inject ``following_error`` (axis stalls), ``over_current`` (fault 0x2310) or ``heartbeat_loss``."""
        with self.lock:
            self.advance()
            if kind == "following_error":
                self.stalled = True
            elif kind == "over_current":
                self._raise_fault(cia402.ERR_OVER_CURRENT)
            elif kind == "heartbeat_loss":
                self.silent = True
            else:
                raise ValueError(f"unknown fault kind {kind!r} (known: {', '.join(FAULT_KINDS)})")

    def clear_injected(self) -> None:
        """Remove injected conditions (the axis follows again, heartbeats resume)."""
        with self.lock:
            self.advance()
            self.stalled = False
            self.silent = False

    def communication_fault(self, code: int = cia402.ERR_HEARTBEAT) -> None:
        """A fault found by a protocol front end (e.g. the master's heartbeat stopped)."""
        with self.lock:
            self.advance()
            self._raise_fault(code)

    def _raise_fault(self, code: int) -> None:
        if self._state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        self._error_code = code
        self._error_register = cia402.error_register_for(code)
        self._following_error_flag = code == cia402.ERR_FOLLOWING_ERROR
        self._state = State.FAULT_REACTION_ACTIVE
        self._set_point_ack = False
        self._pending = None
        self._homing = "idle" if self._homing == "done" else ("error" if self._homing == "running" else "idle")
        for listener in list(self._emcy_listeners):
            listener(self._error_code, self._error_register)

    def _fault_reset(self) -> None:
        self._state = State.SWITCH_ON_DISABLED
        self._error_code = 0
        self._error_register = 0
        self._following_error_flag = False
        self._fe_since = None
        for listener in list(self._emcy_listeners):
            listener(0, 0)

    @property
    def state(self) -> State:
        with self.lock:
            self.advance()
            return self._state

    # ------------------------------------------------------------------------------------------
    # controlword
    # ------------------------------------------------------------------------------------------
    def _on_controlword(self, cw: int) -> None:
        prev = self._cw
        self._cw = cw
        command = cia402.decode_command(cw)
        rising_reset = bool(cw & cia402.CW_FAULT_RESET) and not prev & cia402.CW_FAULT_RESET
        if command is Command.FAULT_RESET and not rising_reset:
            return
        old = self._state
        if old is State.FAULT_REACTION_ACTIVE:
            return
        new = cia402.transition(old, command)
        if old is State.FAULT and new is State.SWITCH_ON_DISABLED:
            self._fault_reset()
            return
        if new is not old:
            self._enter(old, new)
        if self._state is State.OPERATION_ENABLED:
            self._mode_bits(prev, cw)

    def _enter(self, old: State, new: State) -> None:
        self._state = new
        if new is State.OPERATION_ENABLED and old is not State.QUICK_STOP_ACTIVE:
            # power stage on: hold the present position
            self._demand = self._actual
            self._demand_vel = 0.0
            self._target = None
            self._pending = None
            self._target_reached = True
            self._set_point_ack = False
            self._homing = "idle"
        if new not in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            self._power_off()
        if new is State.QUICK_STOP_ACTIVE and int(self._store[(cia402.QUICK_STOP_OPTION, 0)]) == 0:
            self._state = State.SWITCH_ON_DISABLED
            self._power_off()

    def _power_off(self) -> None:
        self._demand = self._actual
        self._demand_vel = 0.0
        self._actual_vel = 0.0
        self._target = None
        self._pending = None
        self._set_point_ack = False
        self._fe_since = None

    def _mode_bits(self, prev: int, cw: int) -> None:
        rising_bit4 = bool(cw & cia402.CW_NEW_SET_POINT) and not prev & cia402.CW_NEW_SET_POINT
        falling_bit4 = not cw & cia402.CW_NEW_SET_POINT and bool(prev & cia402.CW_NEW_SET_POINT)
        if self._mode is Mode.PROFILE_POSITION:
            if rising_bit4 and not self._set_point_ack:
                self._accept_set_point(cw)
            if falling_bit4 and self._pending is None:
                self._set_point_ack = False
        elif self._mode is Mode.HOMING:
            if rising_bit4:
                self._start_homing()
            if falling_bit4 and self._homing == "running":
                self._homing = "idle"  # interrupted

    def _profile_from_store(self) -> _Profile:
        s = self._store
        return _Profile(
            velocity=float(s[(cia402.PROFILE_VELOCITY, 0)]),
            acceleration=max(1.0, float(s[(cia402.PROFILE_ACCELERATION, 0)])),
            deceleration=max(1.0, float(s[(cia402.PROFILE_DECELERATION, 0)])),
        )

    def _limits(self) -> tuple[float, float]:
        lo = float(self._store[(cia402.SOFTWARE_POSITION_LIMIT, 1)]) - self._home_shift
        hi = float(self._store[(cia402.SOFTWARE_POSITION_LIMIT, 2)]) - self._home_shift
        return lo, hi

    def _accept_set_point(self, cw: int) -> None:
        raw = float(int(self._store[(cia402.TARGET_POSITION, 0)]))
        if cw & cia402.CW_RELATIVE:
            base = self._target if self._target is not None else self._demand
            goal = base + raw
        else:
            goal = raw - self._home_shift  # targets are in homed (user) coordinates
        lo, hi = self._limits()
        self._internal_limit = not lo <= goal <= hi
        goal = min(max(goal, lo), hi)
        profile = self._profile_from_store()
        self._set_point_ack = True
        moving = self._target is not None and not self._target_reached
        if cw & cia402.CW_CHANGE_SET_IMMEDIATELY or not moving:
            self._target, self._profile = goal, profile
            self._target_reached = False
            self._in_window_since = None
        else:
            self._pending = (goal, profile)

    def _start_homing(self) -> None:
        method = int(self._store[(cia402.HOMING_METHOD, 0)])
        if method not in SUPPORTED_HOMING_METHODS:
            self._homing = "error"
            return
        self._homing = "running"
        self._homing_phase = "search"
        active = self._switch_active(method, self._demand)
        above = method in (19, 20)
        # inactive: travel towards the switch; active: travel out of it
        self._homing_dir = (1.0 if above else -1.0) * (-1.0 if active else 1.0)
        self._homing_side = self._demand >= self.home_switch_position

    def _switch_active(self, method: int, position: float) -> bool:
        if method in (19, 20):
            return position >= self.home_switch_position
        return position <= self.home_switch_position

    # ------------------------------------------------------------------------------------------
    # statusword
    # ------------------------------------------------------------------------------------------
    def _statusword(self) -> int:
        sw = self._state.bits | cia402.SW_REMOTE
        if self._internal_limit:
            sw |= cia402.SW_INTERNAL_LIMIT
        if self._following_error_flag and self._mode is Mode.PROFILE_POSITION:
            sw |= cia402.SW_FOLLOWING_ERROR
        if self._state is not State.OPERATION_ENABLED:
            if self._state is State.QUICK_STOP_ACTIVE and abs(self._demand_vel) == 0.0:
                sw |= cia402.SW_TARGET_REACHED
            return sw
        halted = bool(self._cw & cia402.CW_HALT)
        if self._mode is Mode.PROFILE_POSITION:
            if self._target_reached or (halted and self._demand_vel == 0.0):
                sw |= cia402.SW_TARGET_REACHED
            if self._set_point_ack:
                sw |= cia402.SW_SET_POINT_ACK
            if self._fe_since is not None:
                sw |= cia402.SW_FOLLOWING_ERROR
        elif self._mode is Mode.PROFILE_VELOCITY:
            goal = 0.0 if halted else float(int(self._store[(cia402.TARGET_VELOCITY, 0)]))
            if abs(self._actual_vel - goal) <= self.velocity_window and abs(self._demand_vel - goal) < 1e-9:
                sw |= cia402.SW_TARGET_REACHED
            if abs(self._actual_vel) <= self.velocity_window:
                sw |= cia402.SW_SPEED_ZERO
        elif self._mode is Mode.HOMING:
            if self._homing == "running" and self._homing_phase == "stop":
                sw |= cia402.SW_HOMING_ATTAINED  # attained, target not reached yet
            elif self._homing == "done":
                sw |= cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED
            elif self._homing == "error":
                sw |= cia402.SW_HOMING_ERROR | cia402.SW_TARGET_REACHED
            elif self._homing == "idle":
                sw |= cia402.SW_TARGET_REACHED
        return sw

    # ------------------------------------------------------------------------------------------
    # physics
    # ------------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def latched(self) -> Iterator[None]:
        """Hold the lock and the drive's time: every read inside sees the same instant (a PDO
        snapshot at SYNC)."""
        with self.lock:
            self.advance()
            self._frozen += 1
            try:
                yield
            finally:
                self._frozen -= 1

    def advance(self, now: float | None = None) -> None:
        """Integrate the motion up to ``now`` (default: the clock's present instant)."""
        with self.lock:
            if self._frozen:
                return
            t_end = self.clock() if now is None else now
            while self._t < t_end:
                dt = min(self.max_step_s, t_end - self._t)
                self._step(dt)
                self._t += dt

    def _step(self, dt: float) -> None:
        state = self._state
        powered = state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
        if not powered:
            return
        # --- trajectory generator
        if state is State.QUICK_STOP_ACTIVE or state is State.FAULT_REACTION_ACTIVE:
            decel = max(1.0, float(self._store[(cia402.QUICK_STOP_DECELERATION, 0)]))
            self._demand_vel = _toward(self._demand_vel, 0.0, decel * dt)
            if self._demand_vel == 0.0:
                if state is State.FAULT_REACTION_ACTIVE:
                    self._state = State.FAULT
                    self._power_off()
                    return
                option = int(self._store[(cia402.QUICK_STOP_OPTION, 0)])
                if option <= 4:
                    self._state = State.SWITCH_ON_DISABLED
                    self._power_off()
                    return
        else:
            self._trajectory(dt)
        error_before = self._demand - self._actual
        demand_before = self._demand
        self._demand += self._demand_vel * dt
        if self._landing:
            self._landing = False
            if self._target is not None:
                self._demand = self._target
            self._demand_vel = 0.0
        # --- the axis follows (first-order servo loop) unless stalled. Exact over the step for a
        # demand moving at constant velocity, so the result does not depend on the step size.
        before = self._actual
        if not self.stalled:
            decay = math.exp(-dt / self.servo_tau_s)
            v = (self._demand - demand_before) / dt
            error = error_before * decay + v * self.servo_tau_s * (1.0 - decay)
            self._actual = self._demand - error
        self._actual_vel = (self._actual - before) / dt
        # --- following error monitor
        window = int(self._store[(cia402.FOLLOWING_ERROR_WINDOW, 0)])
        if window != 0xFFFFFFFF and abs(self._demand - self._actual) > window:
            if self._fe_since is None:
                self._fe_since = self._t
            elif self._t + dt - self._fe_since > int(self._store[(cia402.FOLLOWING_ERROR_TIMEOUT, 0)]) / 1000.0:
                self._raise_fault(cia402.ERR_FOLLOWING_ERROR)
        else:
            self._fe_since = None
        # --- target reached (PP)
        if self._mode is Mode.PROFILE_POSITION and self._target is not None and not self._target_reached:
            if self._demand == self._target and abs(self._actual - self._target) <= int(
                self._store[(cia402.POSITION_WINDOW, 0)]
            ):
                if self._in_window_since is None:
                    self._in_window_since = self._t
                if self._t + dt - self._in_window_since >= int(self._store[(cia402.POSITION_WINDOW_TIME, 0)]) / 1e3:
                    self._target_reached = True
                    if self._pending is not None:
                        self._target, self._profile = self._pending
                        self._pending = None
                        self._target_reached = False
                        self._in_window_since = None
                        if not self._cw & cia402.CW_NEW_SET_POINT:
                            self._set_point_ack = False
            else:
                self._in_window_since = None

    def _trajectory(self, dt: float) -> None:
        halted = bool(self._cw & cia402.CW_HALT)
        mode = self._mode
        lo, hi = self._limits()
        if mode is Mode.HOMING:
            if self._homing == "running":
                self._homing_step(dt)
            else:  # interrupted or finished: come to rest with the homing acceleration
                accel = max(1.0, float(int(self._store[(cia402.HOMING_ACCELERATION, 0)])))
                self._demand_vel = _toward(self._demand_vel, 0.0, accel * dt)
            return
        if mode is Mode.PROFILE_VELOCITY:
            accel = max(1.0, float(self._store[(cia402.PROFILE_ACCELERATION, 0)]))
            decel = max(1.0, float(self._store[(cia402.PROFILE_DECELERATION, 0)]))
            goal = 0.0 if halted else float(int(self._store[(cia402.TARGET_VELOCITY, 0)]))
            speeding_up = abs(goal) > abs(self._demand_vel) and goal * self._demand_vel >= 0
            v = _toward(self._demand_vel, goal, (accel if speeding_up else decel) * dt)
            # software limits: never run past the stopping curve of the limit
            limit_hit = False
            if v > 0:
                cap = math.sqrt(2.0 * decel * max(0.0, hi - self._demand))
                if v > cap:
                    v, limit_hit = cap, True
            elif v < 0:
                cap = math.sqrt(2.0 * decel * max(0.0, self._demand - lo))
                if -v > cap:
                    v, limit_hit = -cap, True
            self._internal_limit = limit_hit
            self._demand_vel = v
            self._snap_to_limits(lo, hi)
            return
        if mode is Mode.PROFILE_POSITION and self._target is not None:
            p = self._profile
            if halted:
                self._demand_vel = _toward(self._demand_vel, 0.0, p.deceleration * dt)
                return
            remaining = self._target - self._demand
            if remaining == 0.0 and self._demand_vel == 0.0:
                return
            direction = 1.0 if remaining > 0 else -1.0
            v = self._demand_vel
            if v * direction < 0:  # moving away from the target: brake first
                self._demand_vel = _toward(v, 0.0, p.deceleration * dt)
                return
            speed = min(abs(v) + p.acceleration * dt, p.velocity, math.sqrt(2.0 * p.deceleration * abs(remaining)))
            if abs(v) > p.velocity:  # cruise velocity lowered while moving
                speed = max(p.velocity, abs(v) - p.deceleration * dt)
                speed = min(speed, math.sqrt(2.0 * p.deceleration * abs(remaining)))
            if speed * dt >= abs(remaining):  # lands within this step: arrive exactly
                self._demand_vel = remaining / dt
                self._landing = True
                return
            self._demand_vel = speed * direction
            return
        # no mode / no target: hold (coming to rest with the profile deceleration)
        decel = max(1.0, float(int(self._store[(cia402.PROFILE_DECELERATION, 0)])))
        self._demand_vel = _toward(self._demand_vel, 0.0, decel * dt)

    def _homing_step(self, dt: float) -> None:
        method = int(self._store[(cia402.HOMING_METHOD, 0)])
        offset = float(int(self._store[(cia402.HOME_OFFSET, 0)]))
        if method in (35, 37):  # the present position is home: shift the encoder reading
            self._demand_vel = 0.0
            self._home_shift = offset - self._actual
            self._demand = self._actual
            self._homing = "done"
            return
        fast = float(int(self._store[(cia402.HOMING_SPEEDS, 1)]))
        slow = float(int(self._store[(cia402.HOMING_SPEEDS, 2)]))
        accel = max(1.0, float(int(self._store[(cia402.HOMING_ACCELERATION, 0)])))
        edge = self.home_switch_position
        side = self._demand >= edge
        crossed = side != self._homing_side  # the demand passed the edge during the last step
        self._homing_side = side
        if self._homing_phase == "search":
            self._demand_vel = _toward(self._demand_vel, self._homing_dir * fast, accel * dt)
            if crossed and self._demand_vel * self._homing_dir > 0:
                self._homing_phase = "back"  # found it: come back slowly to the edge
                self._homing_dir = -self._homing_dir
        elif self._homing_phase == "back":
            self._demand_vel = _toward(self._demand_vel, self._homing_dir * slow, accel * dt)
            if crossed and self._demand_vel * self._homing_dir > 0:
                # the edge position is latched: it reads the home offset from now on
                self._home_shift = offset - edge
                self._homing_phase = "stop"
        else:  # stop after the edge
            self._demand_vel = _toward(self._demand_vel, 0.0, accel * dt)
            if self._demand_vel == 0.0:
                self._homing = "done"

    def _snap_to_limits(self, lo: float, hi: float) -> None:
        if self._demand > hi:
            self._demand, self._demand_vel = hi, 0.0
        elif self._demand < lo:
            self._demand, self._demand_vel = lo, 0.0


def _toward(value: float, goal: float, step: float) -> float:
    if value < goal:
        return min(goal, value + step)
    return max(goal, value - step)


def _i32(x: float) -> int:
    v = round(x)
    return max(-(1 << 31), min((1 << 31) - 1, v))
