"""Field definitions and digital I/O of the simulated LMS100 (what SICK's driver reads at start-up).

Modelled on the LMS111 recording (``tests/data/sick-recordings/``, see ``docs/simulator.md``):

* 30 field definitions, ``field000``..``field029``: by default the first 10 are the unconfigured
  definition the LMS111 answers for its unused fields (scale 1.0, angles on a 0.5 deg grid from
  -45 deg, segmented type, number 0, no geometry, empty name: 32 bytes in CoLa B) and the other 20 the
  one-byte "no definition" answer; any other index is unknown (``sFA 3``). A device can be given its
  own list (e.g. the recorded LMS111's, for replaying its session).
* Four digital inputs, recorded as ``2`` each on the LMS111; their system counter is the device time
  of their last change (0: never changed, as recorded).
* Three switching outputs plus the eight "not used" entries the LMS111 reports (11 in all), each with
  a state (0 inactive, 1 active, 2 not used) and a count of activations; the system counter is the
  device time the message is made.

Nothing in the simulation evaluates fields, so inputs and outputs change only through
:meth:`SimulatedLMS100.set_inputs` / :meth:`SimulatedLMS100.set_outputs`.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.lms100 import FieldGeometry, InputState, InputStateEvent, OutputStateEvent, ScanTime

#: LMS1xx field definitions (field000..field029).
FIELD_COUNT = 30
#: The LMS111 answers full (here: unconfigured) definitions for field000..009, one byte for 010..029.
DEFAULT_FIELDS: tuple[FieldGeometry | None, ...] = (FieldGeometry(),) * 10 + (None,) * 20
SWITCHING_OUTPUTS = 3
UNUSED_OUTPUTS = 8
#: Input state of the recorded LMS111 (all four inputs ``2``).
DEFAULT_INPUTS = (2, 2, 2, 2)
#: Version field of the recorded LMS111's LIDinputstate / LIDoutputstate (the LMS511 sends 0).
IO_VERSION = 1


def scan_time_of(us: int) -> ScanTime:
    """The device's date/time block for device-clock ``us``: 1970-01-01 plus uptime (an unset clock)."""
    secs, micro = divmod(int(us), 1_000_000)
    mins, s = divmod(secs, 60)
    hours, m = divmod(mins, 60)
    return ScanTime(1970, 1, 1 + hours // 24, hours % 24, m, s, micro)


class DeviceIO:
    """Field table, input and output states. Not locked: the owning device calls it under its lock."""

    def __init__(self, fields: Sequence[FieldGeometry | None] = DEFAULT_FIELDS) -> None:
        fields = tuple(fields)
        if not all(f is None or isinstance(f, FieldGeometry) for f in fields) or len(fields) > 1000:
            raise ValueError("fields must be at most 1000 FieldGeometry or None entries")
        self.fields = fields
        self.inputs: tuple[int, int, int, int] = DEFAULT_INPUTS
        self.inputs_changed_us = 0
        self.outputs = [0] * SWITCHING_OUTPUTS
        self.output_counts = [0] * SWITCHING_OUTPUTS

    def field(self, index: int) -> tuple[bool, FieldGeometry | None]:
        """``(known, geometry)`` for field ``index``."""
        if 0 <= index < len(self.fields):
            return True, self.fields[index]
        return False, None

    def set_inputs(self, inputs: Sequence[int], now_us: int) -> bool:
        values = tuple(int(x) for x in inputs)
        if len(values) != 4 or not all(0 <= x <= 255 for x in values):
            raise ValueError(f"inputs must be 4 values 0..255, got {inputs!r}")
        if values == self.inputs:
            return False
        self.inputs = (values[0], values[1], values[2], values[3])
        self.inputs_changed_us = now_us
        return True

    def set_outputs(self, active: Sequence[bool]) -> bool:
        values = [1 if a else 0 for a in active]
        if len(values) != SWITCHING_OUTPUTS:
            raise ValueError(f"an LMS100 has {SWITCHING_OUTPUTS} switching outputs, got {len(values)} values")
        changed = values != self.outputs
        for i, (old, new) in enumerate(zip(self.outputs, values, strict=True)):
            if new and not old:
                self.output_counts[i] = (self.output_counts[i] + 1) % (1 << 32)
        self.outputs = values
        return changed

    @property
    def output_bits(self) -> int:
        """Active outputs as a bit mask (bit 0 = output 1): the scans' first digital-output byte."""
        return sum(1 << i for i, on in enumerate(self.outputs) if on)

    def input_state(self, with_time: bool) -> InputState:
        """``sRA LIDinputstate`` (the time block, if on, is the time of the last change)."""
        time = scan_time_of(self.inputs_changed_us) if with_time else None
        return InputState(IO_VERSION, self.inputs_changed_us % (1 << 32), self.inputs, time)

    def input_state_event(self, with_time: bool) -> InputStateEvent:
        """``sSN LIDinputstate``: the same body as the read."""
        r = self.input_state(with_time)
        return InputStateEvent(r.version, r.system_counter, r.inputs, r.time)

    def output_state(self, now_us: int, with_time: bool) -> OutputStateEvent:
        outputs = tuple(zip(self.outputs, self.output_counts, strict=True)) + ((2, 0),) * UNUSED_OUTPUTS
        return OutputStateEvent(IO_VERSION, now_us % (1 << 32), outputs, scan_time_of(now_us) if with_time else None)
