"""Format readers: ARIS read throughput from the page cache; shared samples -> zarr survey -> back.

Rows (see ``benchmarks/run.py``): ``median_ms`` per whole-file pass; ``note`` gives MB/s or pings/s.
The ARIS target is the issue's 200 MB/s (``target_ms = bytes / 200 MB/s``); the baseline is
``numpy.fromfile`` of the same bytes (a copy from the page cache, the floor for any reader).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from run import DATA, timeit

from sonarmap.io import read_pings
from sonarmap.io.aris import FILE_HEADER_SIZE, ArisFile
from sonarmap.store import open_survey, dataset_to_pings, write_survey

TARGET_MB_S = 200.0


def _aris_rows(path: Path, case: str, repeat: int) -> dict[str, Any]:
    size = path.stat().st_size

    def read_all() -> None:
        with ArisFile(path) as f:
            for ping in f:
                ping.image  # noqa: B018 - decoded float32 image of every frame

    def baseline() -> None:
        np.fromfile(path, dtype=np.uint8)

    ms = timeit(read_all, repeat=repeat)
    base = timeit(baseline, repeat=repeat)
    return {
        "benchmark": "formats",
        "case": case,
        "median_ms": ms,
        "target_ms": size / (TARGET_MB_S * 1e6) * 1e3,
        "baseline": "np.fromfile",
        "baseline_ms": base,
        "note": f"{size / ms / 1e3:.0f} MB/s, {len(ArisFile(path))} frames",
    }


def _big_aris(src: Path, out: Path, n_frames: int) -> Path:
    """A longer ARIS file made by repeating the sample's frames (same headers and data)."""
    raw = src.read_bytes()
    frames = raw[FILE_HEADER_SIZE:]
    reps = -(-n_frames // 6)
    out.write_bytes(raw[:FILE_HEADER_SIZE] + (frames * reps)[: n_frames * (len(frames) // 6)])
    return out


def _zarr_rows(inputs: dict[str, Path], tmp: Path, repeat: int) -> list[dict[str, Any]]:
    rows = []
    for name, path in inputs.items():
        pings = list(read_pings(path))
        store = tmp / f"{name}.zarr"
        counter = iter(range(10**6))

        def write() -> None:  # a fresh store each time: replacing one would time the deletion
            write_survey(pings, tmp / f"{name}-{next(counter)}.zarr", chunk_pings=16)

        def read_back() -> None:
            for p in dataset_to_pings(open_survey(store)):
                p.image  # noqa: B018

        w = timeit(write, repeat=repeat, warmup=1, min_time_s=0.0)
        write_survey(pings, store, chunk_pings=16)
        r = timeit(read_back, repeat=repeat, warmup=1, min_time_s=0.0)
        back = list(dataset_to_pings(open_survey(store)))
        lossless = all(np.array_equal(a.image, b.image) and a.geometry == b.geometry and a.time_ns == b.time_ns
                       for a, b in zip(pings, back, strict=True))
        mb = sum(p.image.nbytes for p in pings) / 1e6
        store_mb = sum(f.stat().st_size for f in store.rglob("*") if f.is_file()) / 1e6
        for op, ms in (("write", w), ("read back", r)):
            rows.append({
                "benchmark": "formats",
                "case": f"{name} -> zarr {op}" if op == "write" else f"zarr -> {name} pings",
                "median_ms": ms,
                "note": f"{len(pings)} pings, {len(pings) / ms * 1e3:.0f} pings/s, {mb / ms * 1e3:.0f} MB/s float32"
                        + (f", store {store_mb:.2f} MB, lossless={lossless}" if op == "write" else ""),
            })
    return rows


def run(quick: bool) -> list[dict[str, Any]]:
    """Benchmark rows (see module docstring)."""
    repeat = 5 if quick else 20
    sample = DATA / "aris" / "sample.aris"
    rows = [_aris_rows(sample, "ARIS read sample.aris (0.58 MB)", repeat)]
    tmp = Path(tempfile.mkdtemp(prefix="sonarmap-bench-"))
    try:
        if not quick:
            big = _big_aris(sample, tmp / "big.aris", 300)
            rows.append(_aris_rows(big, f"ARIS read {big.stat().st_size / 1e6:.0f} MB (300 frames)", 5))
        inputs = {
            "sample.aris": sample,
            "three_pings_8bit.raw": DATA / "oculus" / "three_pings_8bit.raw",
            "didson test (PNG)": DATA / "didson" / "test",
        }
        rows.extend(_zarr_rows(inputs, tmp, 3 if quick else 5))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows
