"""Regenerate the test extracts in this folder from the project's ``shared/reference/sick-recordings/``.

The tests never read ``shared/`` (a user's clone does not have it); they read what this script writes:

* ``<session>.telegrams.json.xz`` for each SICK ``pcap_json_converter`` session (``*.pcapng.json``):
  every telegram of the session, in capture order, as ``{"t": tcp.time_relative, "hex": payload}``,
  plus the source file's name and sha256. Nothing is left out; only the Wireshark-style JSON wrapper
  (which repeats each payload as ``tcp.description`` and adds per-entry boilerplate) is dropped, and
  the result is xz-compressed (the LMS111 session goes from 988 KB to ~97 KB, the LMS511 one from
  2.1 MB to ~219 KB).
* the TiM781S pcapng and the MRS1000 CoLa A text, copied unchanged (small already).

Usage, from the repository root::

    python tests/data/sick-recordings/extract.py            # rewrite the extracts
    python tests/data/sick-recordings/extract.py --check    # exit 1 if they differ from a fresh extract

``--source DIR`` reads another copy of the recordings (default: ``../shared/reference/sick-recordings``
beside the repository).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import lzma
import shutil
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
DEFAULT_SOURCE = HERE.parents[2].parent / "shared" / "reference" / "sick-recordings"
SESSIONS = ("20210302_lms111.pcapng.json", "20210301_lms511.pcapng.json")
COPIES = ("tim781s_scandata_split_segments.pcapng", "mrs1000_cola_a_scandata.txt")


def extract_name(session: str) -> str:
    """``20210302_lms111.pcapng.json`` -> ``20210302_lms111.telegrams.json.xz``."""
    return session.removesuffix(".pcapng.json") + ".telegrams.json.xz"


def session_extract(path: Path) -> dict[str, Any]:
    """The telegrams of one pcap_json_converter session, in order, with their capture times."""
    data = path.read_bytes()
    telegrams = []
    for entry in json.loads(data):
        tcp = entry["_source"]["layers"]["tcp"]
        telegrams.append({"t": tcp["Timestamps"]["tcp.time_relative"], "hex": tcp["tcp.payload"].replace(":", "")})
    return {"source_file": path.name, "source_sha256": hashlib.sha256(data).hexdigest(), "telegrams": telegrams}


def encode(extract: dict[str, Any]) -> bytes:
    text = json.dumps(extract, indent=0, separators=(",", ":")) + "\n"
    return lzma.compress(text.encode("ascii"), preset=9 | lzma.PRESET_EXTREME)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", type=Path, default=DEFAULT_SOURCE)
    ap.add_argument("--check", action="store_true", help="compare with the committed extracts, write nothing")
    args = ap.parse_args(argv)
    src: Path = args.source
    if not src.is_dir():
        print(f"recordings folder not found: {src}", file=sys.stderr)
        return 2
    differ = []
    for session in SESSIONS:
        extract = session_extract(src / session)
        target = HERE / extract_name(session)
        if args.check:
            have = json.loads(lzma.decompress(target.read_bytes())) if target.exists() else None
            if have != extract:
                differ.append(target.name)
        else:
            target.write_bytes(encode(extract))
    for name in COPIES:
        if args.check:
            if not (HERE / name).exists() or (HERE / name).read_bytes() != (src / name).read_bytes():
                differ.append(name)
        else:
            shutil.copyfile(src / name, HERE / name)
    if differ:
        print("differ from a fresh extract: " + ", ".join(differ), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
