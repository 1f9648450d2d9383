"""The recorded SICK telegrams the tests carry (``tests/data/sick-recordings/``, see its README)."""

from __future__ import annotations

import json
import lzma
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

RECORDINGS_DIR = Path(__file__).resolve().parent.parent / "data" / "sick-recordings"

LMS111 = "20210302_lms111"
LMS511 = "20210301_lms511"
TIM781S = "tim781s_scandata_split_segments.pcapng"
MRS1000 = "mrs1000_cola_a_scandata.txt"


@dataclass(frozen=True)
class Telegram:
    """One recorded CoLa B frame and its capture time (s since the start of the capture)."""

    t: float
    frame: bytes

    @property
    def payload(self) -> bytes:
        """The frame without magic, length and checksum."""
        return self.frame[8:-1]


@lru_cache(maxsize=4)
def session(name: str) -> tuple[Telegram, ...]:
    """Every telegram of a recorded CoLa B session (``LMS111`` or ``LMS511``), in capture order."""
    data = json.loads(lzma.decompress((RECORDINGS_DIR / f"{name}.telegrams.json.xz").read_bytes()))
    return tuple(Telegram(float(e["t"]), bytes.fromhex(e["hex"])) for e in data["telegrams"])


def session_frames(name: str) -> tuple[bytes, ...]:
    return tuple(t.frame for t in session(name))
