"""Per-sweep records of a long coverage run (issue 11, item 4), and their summary.

``bench_sensor_model --jsonl FILE`` appends one JSON line per fitted sweep and fit kind: the case
(scene, cloud, fit, edge member, sub-rays, spot held or not), the bench seed and the sweep's index
in that seed's stream, the outcome (``ok`` / ``failed`` / ``gross``), the error and u of the
diameter (m), U = 2 u, whether d +- U covers the truth, the family the model choice picked, the
fitted threshold and spot scale, the fit's CPU and wall time (s) and the tree's commit. A run
started again with the same FILE skips the sweeps already in it (their clouds are still drawn, so
the stream is the same), so a run can be stopped and resumed, and split into chunks over seeds
(``--seed``) or sweeps (``--sweep-range A:B``), each chunk with its own FILE.

The summary pools every FILE given (a sweep logged twice, by overlapping chunks, counts once)::

    python -m bench.coverage_log /work/runs/s10/cov-*.jsonl

per case: sweeps fitted / failed / gross, the coverage k/n of the fitted sweeps with its exact
(Clopper-Pearson) binomial 95 % interval, the mean error +- its standard error, the spread (std),
the mean U, the families picked, the seeds, and the mean CPU seconds per fit.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import beta as beta_dist

#: The fields that name a case: records agreeing on all of them are pooled (a record without
#: ``patterns``, from before that field, had one sub-ray pattern).
CASE_FIELDS = ("scene", "cloud", "fit", "case", "sub_rays", "hold_spot", "patterns")
_CASE_DEFAULTS: dict[str, Any] = {"patterns": 1}


def coverage_interval(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) binomial interval of a coverage of ``k`` in ``n``."""
    if not 0 <= k <= n:
        raise ValueError(f"coverage {k} of {n}: need 0 <= k <= n")
    if n == 0:
        return 0.0, 1.0
    a = (1.0 - level) / 2.0
    lo = 0.0 if k == 0 else float(beta_dist.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta_dist.ppf(1.0 - a, k + 1, n - k))
    return lo, hi


def case_key(rec: dict[str, Any]) -> tuple[Any, ...]:
    return tuple(rec[f] if f in rec else _CASE_DEFAULTS[f] for f in CASE_FIELDS)


def sweep_key(rec: dict[str, Any]) -> tuple[Any, ...]:
    """A sweep's identity: its case, the bench seed and its index in that seed's stream."""
    return (*case_key(rec), rec["seed"], rec["sweep"])


def read_records(paths: Iterable[Path]) -> list[dict[str, Any]]:
    """Every record of the files (missing files are empty; a torn last line, of a run killed
    while writing, is skipped)."""
    out: list[dict[str, Any]] = []
    for path in paths:
        if not path.exists():
            continue
        for line in path.read_text().splitlines():
            if not line.strip():
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


def done_sweeps(path: Path | None) -> set[tuple[Any, ...]]:
    """The sweeps already logged in ``path`` (to skip on resuming)."""
    return set() if path is None else {sweep_key(r) for r in read_records([path])}


def append_record(path: Path, rec: dict[str, Any]) -> None:
    """Append ``rec`` as one line (a non-finite float, such as a weighted fit's threshold, as null)."""
    clean = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in rec.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        f.write(json.dumps(clean, sort_keys=True, allow_nan=False) + "\n")
        f.flush()


def tree_revision() -> str:
    """The commit of the bench's tree (with ``+dirty`` when it has changes), or ``unknown``."""
    here = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + ("+dirty" if dirty else "")


@dataclass
class Summary:
    """One case's pooled records."""

    key: tuple[Any, ...]
    errors: list[float] = field(default_factory=list)
    big_u: list[float] = field(default_factory=list)
    covered: int = 0
    failed: int = 0
    gross: int = 0
    duplicates: int = 0
    cpu: list[float] = field(default_factory=list)
    won: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    seeds: set[int] = field(default_factory=set)
    revs: set[str] = field(default_factory=set)

    @property
    def n(self) -> int:
        return len(self.errors)


def summarize(records: Iterable[dict[str, Any]]) -> list[Summary]:
    """Pool the records per case, each sweep once (the first record of a sweep logged twice)."""
    seen: set[tuple[Any, ...]] = set()
    cases: dict[tuple[Any, ...], Summary] = {}
    for rec in records:
        s = cases.setdefault(case_key(rec), Summary(case_key(rec)))
        if sweep_key(rec) in seen:
            s.duplicates += 1
            continue
        seen.add(sweep_key(rec))
        s.seeds.add(int(rec["seed"]))
        s.revs.add(str(rec.get("rev", "unknown")))
        if rec.get("cpu_s") is not None:
            s.cpu.append(float(rec["cpu_s"]))
        if rec["status"] == "failed":
            s.failed += 1
        elif rec["status"] == "gross":
            s.gross += 1
        else:
            s.errors.append(float(rec["error_m"]))
            s.big_u.append(float(rec["U_m"]))
            s.covered += bool(rec["covered"])
            s.won[str(rec.get("won"))] += 1
    return list(cases.values())


def table(summaries: list[Summary]) -> str:
    lines = [
        "errors and U in mm; covered: |error| <= U = 2 u, of the fitted sweeps, with the exact binomial 95 % interval",
        f"{'case':60s} {'n':>4s} {'fail':>4s} {'covered':>9s} {'95 % interval':>15s} {'mean error':>15s}"
        f" {'std':>6s} {'mean U':>6s} {'cpu s':>6s}  picked / seeds / revs",
    ]
    for s in sorted(summaries, key=lambda s: tuple(str(x) for x in s.key)):
        scene, cloud, fit, case, sub_rays, hold, patterns = s.key
        turned = f" x {patterns} patterns" if patterns != 1 else ""
        name = f"{case} [{fit}, {cloud}, {sub_rays} sub{turned}{', spot held' if hold else ''}] {scene.split(' (')[0]}"
        cpu = f"{np.mean(s.cpu):6.1f}" if s.cpu else f"{'-':>6s}"
        fail = s.failed + s.gross
        if s.n == 0:
            lines.append(f"{name:60s} {0:4d} {fail:4d}  (failed {s.failed}, gross {s.gross})")
            continue
        e, u = 1e3 * np.array(s.errors), 1e3 * np.array(s.big_u)
        sd = float(e.std(ddof=1)) if s.n > 1 else float("nan")
        lo, hi = coverage_interval(s.covered, s.n)
        picked = " ".join(f"{w} x{c}" for w, c in sorted(s.won.items()))
        extra = f"; {s.duplicates} logged twice" if s.duplicates else ""
        lines.append(
            f"{name:60s} {s.n:4d} {fail:4d} {s.covered:4d}/{s.n:<4d} [{100 * lo:5.1f}, {100 * hi:5.1f}] %"
            f" {e.mean():+6.2f} +- {sd / np.sqrt(s.n):4.2f} {sd:6.2f} {u.mean():6.2f} {cpu}"
            f"  {picked} / seeds {','.join(map(str, sorted(s.seeds)))} / {','.join(sorted(s.revs))}{extra}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="JSONL files written by bench_sensor_model --jsonl")
    args = ap.parse_args(argv)
    print(table(summarize(read_records(args.files))))


if __name__ == "__main__":
    main()
