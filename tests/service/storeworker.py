"""One rig's service writing to a shared result store, as a process of its own (the concurrency test).

``python -m tests.service.storeworker URL RIG N START_AT``: opens the store 1 s before wall-clock
time ``START_AT`` (two workers on a new database migrate it at the same moment); from then on,
queue ``N`` measurements and run each through start, progress and finish; every 5th is cancelled
instead, and a schedule is added and marked run. Prints the number of write transactions it made.
"""

from __future__ import annotations

import sys
import time

from service.store import Store


def main(url: str, rig: str, n: int, start_at: float) -> int:
    time.sleep(max(0.0, start_at - time.time() - 1.0))  # both open (and migrate) the store together
    store = Store(url, rig)
    time.sleep(max(0.0, start_at - time.time()))
    writes = 0
    sid = store.add_schedule({"target": "cylinder"}, interval_s=60.0, next_run=0.0, name=rig).id
    writes += 1
    for i in range(n):
        m = store.create_measurement({"i": i, "rig": rig}, schedule_id=sid)
        writes += 1
        if i % 5 == 4:
            store.cancel(m.id)
            writes += 1
            continue
        store.start(m.id)
        store.set_progress(m.id, 0.5, "half")
        store.finish(m.id, {"i": i})
        writes += 3
        store.mark_schedule_run(sid, float(i), float(i + 1), m.id)
        writes += 1
    store.close()
    print(writes)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])))
