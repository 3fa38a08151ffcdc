"""Live processing: the real Oculus packets streamed over loopback at 40 Hz through ``run_live``.

The replay server (``python -m sonarmap.live.server``, its own process, like a sonar) cycles the
three real ``SimplePingResult`` messages of ``oculus/three_pings_8bit.raw`` (703 ranges x 256
beams) at 40 Hz for 60 s (10 s with ``--quick``); the client is :class:`sonarmap.live.OculusTcpSource`
-> :func:`sonarmap.live.run_live` (default pipeline, default queue of 2, drop-oldest) -> a zarr
product store (:class:`sonarmap.live.StoreSink`, flushed every 16 pings / 1 s).

Rows:

* latency p50 / p99 (arrival of the message -> products ready), target p99 <= 25 ms;
* dropped pings (count, in the ``median ms`` column; target 0) and processed / received;
* ``process_ping`` alone, median (for reference: the loop cannot beat it);
* RSS growth of this process from 2 s into the run to its end (MB, target <= 20 MB).

Run with ``python benchmarks/run.py live [--quick]`` or ``python benchmarks/bench_live.py``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("SONARMAP_DATA", HERE.parent.parent / "shared" / "data"))

RATE_HZ = 40.0
P99_TARGET_MS = 25.0
RSS_TARGET_MB = 20.0


def _start_server(capture: Path, duration_s: float) -> tuple[subprocess.Popen[str], int]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "sonarmap.live.server", str(capture), "--rate", str(RATE_HZ), "--port", "0",
         "--duration", str(duration_s)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("listening on "):
        proc.kill()
        raise RuntimeError(f"replay server did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}")
    return proc, int(line.rsplit(":", 1)[1])


def run(quick: bool = False) -> list[dict[str, Any]]:
    import psutil

    from sonarmap.live import OculusTcpSource, StoreSink, run_live, warm_pipeline

    duration = 10.0 if quick else 60.0
    capture = DATA / "oculus" / "three_pings_8bit.raw"
    warm_pipeline()
    me = psutil.Process()
    rss: dict[str, float] = {}

    def sample() -> None:
        time.sleep(2.0)
        rss["start"] = me.memory_info().rss / 2**20

    with tempfile.TemporaryDirectory() as tmp:
        server, port = _start_server(capture, duration)
        try:
            store = StoreSink(Path(tmp) / "live.zarr", config=None)
            threading.Thread(target=sample, daemon=True).start()
            stats = run_live(OculusTcpSource("127.0.0.1", port), sinks=[store], duration_s=duration)
            store.close()
            rss["end"] = me.memory_info().rss / 2**20
        finally:
            server.kill()
            server.wait()
    growth = rss["end"] - rss.get("start", rss["end"])
    case = f"tcp {RATE_HZ:g} Hz, {duration:g} s, Oculus 703x256"
    note = (f"{stats.count} processed of {stats.received} received ({stats.pings_per_s:.1f}/s), "
            f"queue 2, drop-oldest, store flushed every 16 pings")
    return [
        {"benchmark": "live", "case": f"{case}: latency p50", "median_ms": stats.latency_p50_ms, "note": note},
        {"benchmark": "live", "case": f"{case}: latency p99", "median_ms": stats.latency_p99_ms,
         "target_ms": P99_TARGET_MS, "note": f"max {stats.latency_max_ms:.1f} ms"},
        {"benchmark": "live", "case": f"{case}: dropped pings (count)", "median_ms": float(stats.drops),
         "target_ms": 0.0, "note": f"{100 * stats.drops / max(1, stats.received):.0f} % of received"},
        {"benchmark": "live", "case": f"{case}: process_ping alone, median", "median_ms": stats.process_p50_ms},
        {"benchmark": "live", "case": f"{case}: RSS growth (MB)", "median_ms": growth, "target_ms": RSS_TARGET_MB,
         "note": f"{rss.get('start', float('nan')):.0f} -> {rss['end']:.0f} MB"},
    ]


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv):
        print(row)
