"""Seeded fuzzing of every reader: seed files, mutations, and a sandboxed worker.

A case is a mutated copy of a seed input (a real recording or a file from the package's own
writers): truncation, bit flips, extreme header values, deleted or corrupted store files, deep or
absurd JSON, and non-regular files (FIFOs, ``/dev/zero``).  Each case is read by a persistent
worker subprocess (``fuzz_worker.py``) with a capped address space; a case that runs longer than the
time limit is a hang: the worker is killed and restarted.  Outcomes are counted per reader.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import struct
import subprocess
import sys
import time
import zlib
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFECTS = ("foreign", "bad_value", "memory", "hang")

#: Values written over 4 or 8 header bytes.
_U32 = (0, 1, 0xFFFFFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFF, 0x10000)
_F32 = (float("nan"), float("inf"), float("-inf"), 3.4e38, -3.4e38, 1e-38, 0.0, -1.0)
_F64 = (float("nan"), float("inf"), float("-inf"), 1.7e308, -1.7e308, 0.0)


class Worker:
    """A persistent reader subprocess with a memory cap and a per-case time limit."""

    def __init__(self, *, time_limit_s: float = 10.0, headroom_mb: int = 1024) -> None:
        self.time_limit_s = time_limit_s
        self.headroom_mb = headroom_mb
        self.proc: subprocess.Popen[str] | None = None

    def _start(self) -> None:
        env = dict(os.environ)
        env.setdefault("NUMBA_NUM_THREADS", "1")
        self.proc = subprocess.Popen(
            [sys.executable, str(HERE / "fuzz_worker.py"), "--headroom-mb", str(self.headroom_mb)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env,
        )
        line = self._readline(120.0)
        if line is None or "ready" not in line:
            raise RuntimeError("fuzz worker did not start")

    def _readline(self, timeout: float) -> str | None:
        assert self.proc is not None and self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        if not ready:
            return None
        line = self.proc.stdout.readline()
        return line or None

    def run(self, path: Path, time_limit_s: float | None = None) -> dict[str, str]:
        """Read ``path`` in the worker; ``{"outcome", "detail"}``.  ``time_limit_s`` replaces the
        per-case limit for this read (the seed's first read in a fresh worker may compile the
        reader's kernels, which takes longer than any case should on a loaded machine)."""
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"path": str(path)}) + "\n")
        self.proc.stdin.flush()
        t0 = time.monotonic()
        line = self._readline(self.time_limit_s if time_limit_s is None else time_limit_s)
        if line is None:
            crashed = self.proc.poll() is not None
            self.close()
            if crashed:
                return {"outcome": "foreign", "detail": "worker crashed"}
            return {"outcome": "hang", "detail": f"no answer in {time.monotonic() - t0:.1f} s"}
        return json.loads(line)

    def close(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


# --------------------------------------------------------------------------------------- mutations
def _bytes_mutation(data: bytes, rng: np.random.Generator, header_bytes: int) -> bytes:
    """One random mutation of a binary file's bytes."""
    buf = bytearray(data)
    n = len(buf)
    kind = rng.integers(0, 6)
    if n == 0:
        return bytes(buf)
    if kind == 0:  # truncate
        return bytes(buf[: int(rng.integers(0, n))])
    if kind == 1:  # a few bit flips anywhere
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(0, n))
            buf[i] ^= 1 << int(rng.integers(0, 8))
        return bytes(buf)
    span = max(1, min(n, header_bytes))
    if kind == 2:  # extreme uint32 in the header
        i = int(rng.integers(0, max(1, span - 4)))
        buf[i : i + 4] = struct.pack("<I", int(rng.choice(_U32)))[: n - i]
    elif kind == 3:  # extreme float32 in the header
        i = int(rng.integers(0, max(1, span - 4)))
        buf[i : i + 4] = struct.pack("<f", float(rng.choice(_F32)))[: n - i]
    elif kind == 4:  # extreme float64 in the header
        i = int(rng.integers(0, max(1, span - 8)))
        buf[i : i + 8] = struct.pack("<d", float(rng.choice(_F64)))[: n - i]
    else:  # a run of 0x00 or 0xFF bytes, or a duplicated block
        i = int(rng.integers(0, n))
        k = int(rng.integers(1, 65))
        if rng.random() < 0.5:
            buf[i : i + k] = (b"\xff" if rng.random() < 0.5 else b"\x00") * len(buf[i : i + k])
        else:
            buf[i:i] = buf[i : i + k]
    return bytes(buf)


_JSON_VALUES: tuple[object, ...] = (
    0, -1, 0.5, 1e308, -1e308, float("nan"), float("inf"), True, False, None, "x", [], {}, [1, 2],
    10**6, 10**9, 2**63, -(2**63) - 1,
)


def _json_mutation(text: str, rng: np.random.Generator) -> str:
    """One random structural mutation of a JSON document."""
    kind = rng.integers(0, 6)
    if kind == 0:
        return "[" * 100_000
    if kind == 1:
        return text[: int(rng.integers(0, max(1, len(text))))]
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError):
        return text
    if not isinstance(doc, dict) or not doc:
        return text
    key = str(rng.choice(sorted(doc)))
    if kind == 2:
        del doc[key]
        return json.dumps(doc)
    if kind == 3:  # a 5000-digit integer
        return json.dumps({**doc, key: 0}).replace(f'"{key}": 0', f'"{key}": ' + "9" * 5000)
    if kind == 4 and isinstance(doc[key], list) and doc[key]:
        lst = list(doc[key])
        j = int(rng.integers(0, len(lst)))
        lst[j] = _JSON_VALUES[int(rng.integers(0, len(_JSON_VALUES)))]
        doc[key] = lst if rng.random() < 0.7 else lst[: int(rng.integers(0, len(lst)))]
        return json.dumps(doc)
    doc[key] = _JSON_VALUES[int(rng.integers(0, len(_JSON_VALUES)))]
    return json.dumps(doc)


def _mutate_file(path: Path, rng: np.random.Generator, header_bytes: int) -> None:
    if path.suffix == ".json" or path.name in {"zarr.json", ".zarray", ".zattrs", ".zgroup"}:
        text = path.read_text(errors="replace")
        if rng.random() < 0.85:
            path.write_text(_json_mutation(text, rng))
            return
    path.write_bytes(_bytes_mutation(path.read_bytes(), rng, header_bytes))


# ------------------------------------------------------------------------------------------- seeds
@dataclass
class Seed:
    """A reader's seed input: one file or directory (``main``) plus the files mutated with it."""

    name: str
    main: Path
    header_bytes: int = 1024
    #: For a directory seed: mutate files under it; for a file seed: mutate it or its siblings.
    files: list[Path] = field(default_factory=list)


def make_case(seed: Seed, case_dir: Path, index: int) -> Path:
    """Copy the seed into ``case_dir`` and apply the ``index``-th seeded mutation; the path to read."""
    rng = np.random.default_rng([zlib.crc32(seed.name.encode()), index])
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    special = index % 50
    if seed.main.is_dir():
        target = case_dir / seed.main.name
        shutil.copytree(seed.main, target)
        files = sorted(p for p in target.rglob("*") if p.is_file())
    else:
        for f in [seed.main, *seed.files]:
            shutil.copy2(f, case_dir / f.name)
        target = case_dir / seed.main.name
        files = [case_dir / f.name for f in [seed.main, *seed.files]]
    if special == 1:  # a FIFO where a file should be
        victim = files[int(rng.integers(0, len(files)))]
        victim.unlink()
        os.mkfifo(victim)
        return target
    if special == 2:  # a symlink to an endless device
        victim = files[int(rng.integers(0, len(files)))]
        victim.unlink()
        victim.symlink_to("/dev/zero")
        return target
    if special == 3:  # an empty file
        files[int(rng.integers(0, len(files)))].write_bytes(b"")
        return target
    if seed.main.is_dir() and rng.random() < 0.15:  # a file of the store/bag deleted
        files[int(rng.integers(0, len(files)))].unlink()
        return target
    n_mut = 1 if rng.random() < 0.7 else int(rng.integers(2, 4))
    for _ in range(n_mut):
        victim = files[int(rng.integers(0, len(files)))]
        _mutate_file(victim, rng, seed.header_bytes)
    return target


@dataclass
class Result:
    """Outcome counts of one reader's fuzz run, with an example per defect kind."""

    reader: str
    counts: Counter[str] = field(default_factory=Counter)
    examples: dict[str, str] = field(default_factory=dict)

    @property
    def defects(self) -> int:
        return sum(self.counts[k] for k in DEFECTS)

    def row(self) -> str:
        c = self.counts
        return (f"| {self.reader} | {sum(c.values())} | {c['ok']} | {c['error']} | {c['foreign']} | "
                f"{c['hang']} | {c['memory']} | {c['bad_value']} |")


def fuzz(seed: Seed, work: Path, n_cases: int, worker: Worker,
         progress: Callable[[int], None] | None = None) -> Result:
    """Run ``n_cases`` seeded cases of ``seed`` through ``worker``."""
    res = Result(seed.name)
    for i in range(n_cases):
        target = make_case(seed, work / seed.name, i)
        out = worker.run(target)
        res.counts[out["outcome"]] += 1
        if out["outcome"] in DEFECTS and out["outcome"] not in res.examples:
            res.examples[out["outcome"]] = f"case {i}: {out['detail']}"
        if progress is not None:
            progress(i)
    # leave no FIFO behind for later tests' directory scans
    shutil.rmtree(work / seed.name, ignore_errors=True)
    return res
