"""Fuzz suite: every reader, seeded mutations of real and written files, in a sandboxed worker.

Each case must end in one of two ways: pings whose values are all in their documented range, or a
:class:`sonarmap.errors.SonarmapError`.  A foreign exception, a hang over the time limit, a case
needing more than the memory headroom, or an out-of-range value fails the reader's test, which then
prints the outcome table and one example per defect.

The default run reads ``--fuzz-cases`` (200) cases per reader; ``--fuzz-cases 1000`` (or more) is
the long run::

    python -m pytest -q tests/io/test_fuzz.py --fuzz-cases 1000 -s
"""

from __future__ import annotations

import datetime as dt
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from fuzzing import Result, Seed, Worker, fuzz

READERS = ("pngjson", "aris", "oculus", "viewpoint_v1", "viewpoint_v2", "ddf", "rosbag1", "rosbag2",
           "zarr", "kongsberg", "kmall")

_RESULTS: list[Result] = []


@pytest.fixture(scope="module")
def worker() -> Iterator[Worker]:
    w = Worker(time_limit_s=10.0, headroom_mb=1024)
    yield w
    w.close()
    if _RESULTS:
        print("\n| reader | cases | ok | clean error | foreign | hang >10 s | memory >1 GB | out of range |")
        print("|---|---|---|---|---|---|---|---|")
        for r in _RESULTS:
            print(r.row())


def _small_pings(n: int, bins: int = 64, beams: int = 16) -> list:
    from sonarmap.geometry import SonarGeometry
    from sonarmap.ping import Ping

    g = SonarGeometry(azimuth_rad=np.linspace(-0.3, 0.3, beams), range_m=np.linspace(1.0, 5.0, bins))
    rng = np.random.default_rng(1)
    t0 = 1_600_000_000_000_000_000
    return [Ping(rng.random((bins, beams), dtype=np.float32), g, time_ns=t0 + i * 100_000_000,
                 source=f"sim#{i}") for i in range(n)]


def _seed(name: str, data_dir: Path, root: Path) -> Seed:
    d = root / name
    d.mkdir(parents=True, exist_ok=True)
    if name == "pngjson":
        src = sorted((data_dir / "didson" / "test").glob("*_raw.png"))[0]
        png = shutil.copy2(src, d / src.name)
        side = shutil.copy2(src.with_name(src.name.replace("_raw.png", ".json")), d)
        return Seed(name, Path(png), header_bytes=128, files=[Path(side)])
    if name == "aris":
        raw = (data_dir / "aris" / "sample.aris").read_bytes()
        frame = 1024 + 48 * 2000
        p = d / "sample.aris"
        p.write_bytes(raw[: 1024 + 2 * frame])
        return Seed(name, p, header_bytes=2048)
    if name == "oculus":
        p = Path(shutil.copy2(data_dir / "oculus" / "three_pings_8bit.raw", d))
        return Seed(name, p, header_bytes=400)
    if name.startswith("viewpoint"):
        from oculus_writer import encode_ping, write_log_v1, write_log_v2

        rng = np.random.default_rng(0)
        bearings = np.linspace(-6500, 6500, 32).round().astype(np.int16)
        msgs = [encode_ping(rng.integers(0, 256, (100, 32), dtype=np.uint8), bearings, version=v)
                for v in (1, 2)]
        p = d / "log.oculus"
        if name == "viewpoint_v1":
            write_log_v1(p, msgs, [1.6e9, 1.6e9 + 0.1], compress=True)
        else:
            write_log_v2(p, msgs, [1.6e9, 1.6e9 + 0.1])
        return Seed(name, p, header_bytes=600)
    if name == "ddf":
        from ddf_writer import write_ddf

        rng = np.random.default_rng(0)
        frames = [rng.integers(0, 256, (128, 96), dtype=np.uint8) for _ in range(2)]
        p = d / "a.ddf"
        write_ddf(p, frames, start_time=dt.datetime(2016, 7, 19, 14, 3, 5, tzinfo=dt.UTC))
        return Seed(name, p, header_bytes=1200)
    if name.startswith("rosbag"):
        from sonarmap.io.rosbag import write_bag

        version = int(name[-1])
        p = d / ("s.bag" if version == 1 else "s_bag")
        write_bag(_small_pings(2), p, version=version)
        return Seed(name, p, header_bytes=4096)
    if name == "zarr":
        from sonarmap.store import write_survey

        p = d / "s.zarr"
        write_survey(_small_pings(3), p, chunk_pings=2)
        return Seed(name, p, header_bytes=256)
    if name == "kongsberg":
        from sonarmap.io import FORMAT_MODULES

        if "kongsberg" not in FORMAT_MODULES:
            pytest.skip("no Kongsberg reader")
        k = data_dir / "kongsberg"
        wcd = Path(shutil.copy2(k / "0077_20221109_123655_Belgica.wcd", d))
        al = Path(shutil.copy2(k / "0077_20221109_123655_Belgica.all", d))
        return Seed(name, al, header_bytes=4096, files=[wcd])
    if name == "kmall":
        from kmall_writer import write_kmall

        p = d / "0001_synthetic.kmall"
        write_kmall(p)
        return Seed(name, p, header_bytes=2048)
    raise AssertionError(name)


@pytest.mark.parametrize("reader", READERS)
@pytest.mark.slow
def test_fuzz_reader(reader: str, worker: Worker, data_dir: Path, tmp_path_factory: pytest.TempPathFactory,
                     request: pytest.FixtureRequest) -> None:
    n_cases = int(request.config.getoption("--fuzz-cases"))
    root = tmp_path_factory.mktemp(f"fuzz_{reader}")
    seed = _seed(reader, data_dir, root / "seed")
    # (the seed is no case: its read warms the worker - imports, the reader's kernels compiled into
    # the cache when they are not yet - so it gets the start-up's time, not a case's 10 s)
    base = worker.run(seed.main, time_limit_s=120.0)
    assert base["outcome"] == "ok", f"seed does not read cleanly: {base}"
    res = fuzz(seed, root / "cases", n_cases, worker)
    _RESULTS.append(res)
    assert res.defects == 0, f"{reader}: {dict(res.counts)}; examples: {res.examples}"
