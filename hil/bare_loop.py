"""The bare sleep loop ``hil.pace`` judges loop runs against, scheduled as a module's cycles are
(dh2rt.runtime.ModuleRuntime.run): a cycle that starts more than ``tolerance`` periods after its
deadline is late, and the schedule restarts from now rather than bursting.

It imports nothing of dh2rt's, so that ``python -S -m hil.bare_loop PERIOD TOLERANCE`` (the
witness beside a loop run, :class:`hil.pace.Witness`) starts in tens of milliseconds: run so,
it keeps each cycle's lateness (microseconds) until SIGTERM and then prints them on one line.
"""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Iterator
from types import FrameType


def lateness(period_s: float, tolerance: float) -> Iterator[float]:
    """Each cycle's lateness (s, 0 when on time), one a period, for as long as it is asked."""
    deadline = time.monotonic()
    while True:
        now = time.monotonic()
        late = now - deadline
        yield max(0.0, late)
        if late > tolerance * period_s:
            deadline = now
        deadline += period_s
        time.sleep(max(0.0, deadline - time.monotonic()))


def _stop(_signum: int, _frame: FrameType | None) -> None:
    raise SystemExit


def main(argv: list[str]) -> None:
    period_s, tolerance = float(argv[0]), float(argv[1])
    late: list[int] = []
    signal.signal(signal.SIGTERM, _stop)
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    try:
        for x in lateness(period_s, tolerance):
            late.append(round(x * 1e6))
    except SystemExit:
        pass
    sys.stdout.write(" ".join(map(str, late)) + "\n")
    sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv[1:])
