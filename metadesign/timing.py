"""Wall-clock timing of a call, the one way benchmarks and latency studies measure it."""

from __future__ import annotations

import time
from typing import Callable

__all__ = ["repeat_seconds"]


def repeat_seconds(fn: Callable[[], object], n: int = 5, stat: str = "median",
                   sync: Callable[[], object] | None = None) -> float:
    """Seconds per call of ``fn``: one warm-up call, then ``n`` timed calls; their median, or their
    minimum (``stat="min"``: the run least disturbed by other work on shared cores).  ``sync`` (e.g.
    ``torch.cuda.synchronize``) is called after each call, inside the timed interval."""
    if stat not in ("median", "min"):
        raise ValueError(f"stat: expected median or min, got {stat!r}")
    fn()
    if sync:
        sync()
    ts = []
    for _ in range(max(int(n), 1)):
        t0 = time.perf_counter()
        fn()
        if sync:
            sync()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    return float(ts[0] if stat == "min" else ts[len(ts) // 2])
