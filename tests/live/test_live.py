"""``sonarmap live``: sources, the real-time loop, the growing store, the CLI.

Real data: the liboculus capture (``oculus/three_pings_8bit.raw``) served over loopback by the
replay server, and ``aris/sample.aris`` written progressively into a temporary file.  Rates are
chosen so that the default pipeline (~30-80 ms per 703 x 256 Oculus ping on the shared 2-CPU
machine) keeps up where a test needs "no drops", and far beyond where it needs drops.
"""

from __future__ import annotations

import io
import json
import math
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.live import (
    FollowSource,
    MessageFramer,
    OculusTcpSource,
    ReplayServer,
    ReplaySource,
    SourceError,
    StoreSink,
    decode_fire_message,
    encode_fire_message,
    open_source,
    run_live,
    warm_pipeline,
)
from sonarmap.survey import load_products, open_products

#: The replay server closes the connection after its last message: the client says so once.
pytestmark = pytest.mark.filterwarnings("ignore:.*connection lost; reconnecting")


@pytest.fixture(scope="module")
def raw_capture(data_dir: Path) -> Path:
    p = data_dir / "oculus" / "three_pings_8bit.raw"
    assert p.is_file()
    return p


@pytest.fixture(scope="module")
def aris_file(data_dir: Path) -> Path:
    p = data_dir / "aris" / "sample.aris"
    assert p.is_file()
    return p


@pytest.fixture(scope="module", autouse=True)
def _warm() -> None:
    warm_pipeline()


class Collect:
    """A sink that remembers each ping's id, source and the time its products were ready."""

    def __init__(self) -> None:
        self.ids: list[int] = []
        self.sources: list[str] = []
        self.done_at: list[float] = []
        self.n = 0

    def write(self, ping: Any, products: Any) -> None:
        self.ids.append(int(ping.meta.get("ping_id", -1)))
        self.sources.append(ping.source)
        self.done_at.append(time.monotonic())
        self.n += 1


# ---------------------------------------------------------------------------- protocol
def test_fire_message_round_trip_and_layout() -> None:
    msg = encode_fire_message()
    assert len(msg) == 16 + 37 and msg[:2] == b"SO"
    oid, _s, _d, msg_id, _v, payload, _sp = struct.unpack_from("<HHHHHIH", msg, 0)
    assert (oid, msg_id, payload) == (0x4F53, 0x15, 37)
    assert decode_fire_message(msg).range_m == 2.0


def test_framer_resyncs_on_damage_at_any_split(raw_capture: Path) -> None:
    from sonarmap.live.server import read_capture_messages

    msgs = read_capture_messages(raw_capture)
    bad = bytearray(msgs[1])
    bad[:2] = b"XX"  # lost, one malformed event
    stream = (b"\x00garbage SOx" + msgs[0] + bytes(bad) + msgs[2] + b"S" * 50 + msgs[0])
    for step in (101, 977, 65536, len(stream)):
        fr = MessageFramer()
        out = []
        for i in range(0, len(stream), step):
            out += fr.feed(stream[i : i + step])
        assert [m for _, m in out] == [msgs[0], msgs[2], msgs[0]], step
        assert fr.malformed == 3, step  # leading garbage, the bad magic, the run of b"S"


# ---------------------------------------------------------------------------- TCP source + loop
@pytest.mark.slow
def test_tcp_replay_every_ping_processed_without_drops(raw_capture: Path, tmp_path: Path) -> None:
    n = 30
    with ReplayServer(raw_capture, rate_hz=10, count=n) as srv:
        col = Collect()
        store = StoreSink(tmp_path / "s.zarr", config=None, flush_every=8)
        stats = run_live(OculusTcpSource("127.0.0.1", srv.port), sinks=[col, store], max_pings=n, queue_size=64)
        store.close()
        assert srv.fire is not None and srv.fire.range_m == 2.0  # the client fired the sonar
    assert stats.count == n and stats.drops == 0 and stats.malformed == 0, stats
    assert col.ids == list(range(n))  # every ping, in order, once
    assert stats.latency_p50_ms < 1000 and not math.isnan(stats.latency_p99_ms)
    ds = load_products(tmp_path / "s.zarr")
    assert ds.sizes["ping_time"] == n and list(ds["source"].values) == col.sources
    assert ds.attrs["live_status"] == "complete"
    t = ds["ping_time"].values.astype("int64")
    assert np.all(np.diff(t) > 0)  # receive times


@pytest.mark.slow
def test_unsustainable_rate_drops_oldest_and_latency_stays_bounded(raw_capture: Path) -> None:
    # 1000 Hz: a ping takes ~4 ms to process here, so 200 Hz could be sustained on a fast machine.
    with ReplayServer(raw_capture, rate_hz=1000) as srv:
        col = Collect()
        stats = run_live(OculusTcpSource("127.0.0.1", srv.port), sinks=[col], duration_s=1.5, queue_size=2)
    # Read after the server thread is joined: a message the client already received may not be
    # counted yet while the thread that sent it is still between sendall() and its counter.
    sent = srv.sent_valid
    assert stats.drops > 0 and stats.count > 0, stats
    assert stats.received == stats.count + stats.drops + stats.unprocessed
    assert stats.received <= sent
    assert col.ids == sorted(col.ids)  # newest kept: ids only move forward
    # Bounded: at most the queue (2) + the ping in work + scheduling slack, never the ~1.5 s an
    # unbounded queue reaches after 1.5 s at 1000 Hz.
    assert stats.latency_p99_ms < 8 * stats.process_p50_ms + 100, stats


@pytest.mark.slow
def test_server_restart_reconnects_and_store_is_complete(raw_capture: Path, tmp_path: Path) -> None:
    srv = ReplayServer(raw_capture, rate_hz=10).start()
    col = Collect()
    store = StoreSink(tmp_path / "r.zarr", config=None, flush_every=4)
    src = OculusTcpSource("127.0.0.1", srv.port, backoff_s=0.05, max_backoff_s=0.2)
    out: dict[str, Any] = {}
    th = threading.Thread(target=lambda: out.update(stats=run_live(src, sinks=[col, store], max_pings=20,
                                                                    queue_size=64)))
    th.start()
    try:
        t0 = time.monotonic()
        while col.n < 8 and time.monotonic() - t0 < 10:
            time.sleep(0.02)
        srv.stop()  # the sonar goes away ...
        time.sleep(0.4)
        srv.start()  # ... and comes back on the same port
        th.join(20)
    finally:
        srv.stop()
        src.stop()
        th.join(5)
        store.close()
    stats = out["stats"]
    assert stats.count == 20 and stats.reconnects >= 1, stats
    assert col.ids == sorted(set(col.ids))  # increasing, no duplicates (some lost in the outage)
    ds = load_products(tmp_path / "r.zarr")
    assert ds.sizes["ping_time"] == 20 and list(ds["source"].values) == col.sources


@pytest.mark.slow
def test_corrupted_packets_are_counted_and_skipped(raw_capture: Path) -> None:
    n = 25  # the last one intact: every damaged message arrives before the last ping
    with ReplayServer(raw_capture, rate_hz=12, count=n, corrupt_every=4) as srv:
        col = Collect()
        src = OculusTcpSource("127.0.0.1", srv.port, max_retries=0, read_timeout_s=1.0)
        with pytest.warns(UserWarning, match="damaged"):
            stats = run_live(src, sinks=[col], max_pings=n - 4, queue_size=64, duration_s=8)
        assert srv.corrupted == 6
    # 6 damaged: 2 junk runs before intact pings, 2 broken magics, 2 broken image sizes (lost)
    assert stats.malformed == 6, stats
    assert stats.count == n - 4 and stats.drops == 0
    lost = {i for i in range(n) if (i + 1) % 4 == 0 and ((i + 1) // 4 - 1) % 3 != 0}
    assert col.ids == [i for i in range(n) if i not in lost]


def test_cannot_connect_is_a_source_error() -> None:
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nobody listens there
    src = OculusTcpSource("127.0.0.1", port, max_retries=1, backoff_s=0.01)
    with pytest.raises(SourceError, match="cannot connect after 2 attempts"):
        run_live(src, max_pings=1)


def test_a_refused_connection_warns_once_while_it_retries() -> None:
    """A wrong address says so at the first refusal (one warning line), not only when the retries
    run out - a run with --duration shorter than the retries would otherwise end silently."""
    import socket
    import warnings

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    src = OculusTcpSource("127.0.0.1", port, max_retries=3, backoff_s=0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(SourceError, match="cannot connect after 4 attempts"):
            run_live(src, max_pings=1)
    assert [w for w in src.warnings if "cannot connect" in w] == [
        f"tcp://127.0.0.1:{port}: cannot connect (Connection refused); retrying, up to 3 more times"]


# ---------------------------------------------------------------------------- follow + batch equality
def _write_progressively(src: Path, dst: Path, interval_s: float, written_at: list[float]) -> None:
    from sonarmap.io.aris import FILE_HEADER_SIZE, ArisFile

    with ArisFile(src) as f:
        frame = f.frame_size
        n = len(f)
    data = src.read_bytes()
    with open(dst, "wb") as fh:
        fh.write(data[:FILE_HEADER_SIZE])
        fh.flush()
        for i in range(n):
            time.sleep(interval_s)
            a = FILE_HEADER_SIZE + i * frame
            fh.write(data[a : a + frame // 2])  # half a frame: not yet readable
            fh.flush()
            time.sleep(0.02)
            fh.write(data[a + frame // 2 : a + frame])
            fh.flush()
            written_at.append(time.monotonic())


@pytest.mark.slow
def test_follow_aris_processes_each_frame_within_a_ping_interval_and_equals_batch(
        aris_file: Path, tmp_path: Path) -> None:
    from sonarmap.survey import process_survey

    growing = tmp_path / "growing.aris"
    interval = 0.25
    written_at: list[float] = []
    writer = threading.Thread(target=_write_progressively, args=(aris_file, growing, interval, written_at))
    writer.start()
    col = Collect()
    store = StoreSink(tmp_path / "live.zarr", config=None, flush_every=2)
    try:
        stats = run_live(FollowSource(growing, idle_timeout_s=0.6, poll_s=0.01), sinks=[col, store], queue_size=8)
    finally:
        writer.join()
        store.close()
    assert stats.count == 6 and stats.drops == 0 and stats.stopped_by == "source"
    lag = np.asarray(col.done_at) - np.asarray(written_at)
    assert np.all(lag > 0) and np.all(lag < interval), lag
    # the live store equals the batch store of the same pings, variable by variable
    process_survey([growing], tmp_path / "batch.zarr", workers=0)
    live, batch = load_products(tmp_path / "live.zarr"), load_products(tmp_path / "batch.zarr")
    assert set(live.variables) == set(batch.variables)
    for name in batch.variables:
        a, b = live[name].values, batch[name].values
        assert a.shape == b.shape and a.dtype == b.dtype, name
        if a.dtype.kind == "f":
            assert np.array_equal(a, b, equal_nan=True), name
        else:
            assert np.array_equal(a, b), name


def test_replay_source_keeps_recorded_times_and_rate(aris_file: Path) -> None:
    from sonarmap.io import read_pings

    col = Collect()
    t0 = time.monotonic()
    stats = run_live(ReplaySource(aris_file, rate_hz=20), sinks=[col], queue_size=8)
    assert stats.count == 6 and time.monotonic() - t0 >= 5 / 20
    assert col.sources == [p.source for p in read_pings(str(aris_file))]


def test_open_source_forms(aris_file: Path) -> None:
    assert isinstance(open_source("oculus://10.0.0.2"), OculusTcpSource)
    assert open_source("tcp://[::1]:9000").port == 9000  # type: ignore[attr-defined]
    assert isinstance(open_source(str(aris_file), follow=True), FollowSource)
    with pytest.raises(InputError, match="--follow"):
        open_source(str(aris_file))
    with pytest.raises(InputError, match="port"):
        open_source("tcp://host:99999")


# ---------------------------------------------------------------------------- store readable while written
@pytest.mark.slow
def test_store_reads_as_a_consistent_prefix_while_written(oculus_pings: list, tmp_path: Path) -> None:
    import xarray as xr

    from sonarmap.pipeline import process_ping

    prods = [process_ping(p) for p in oculus_pings]
    path = tmp_path / "grow.zarr"
    sink = StoreSink(path, config=None, flush_every=1)
    seen: list[int] = []
    errors: list[BaseException] = []
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            if not (path / "zarr.json").exists():
                time.sleep(0.01)
                continue
            try:
                ds = open_products(path)
                n = ds.sizes["ping_time"]
                assert np.all(ds["ping_time"].values.astype("int64") > 0)  # no unwritten rows
                assert ds["range"].shape[0] == n and ds["source"].shape[0] == n
                dz = xr.open_zarr(path, zarr_format=3)
                assert np.all(dz["ping_time"].values.astype("int64") > 0)
                seen.append(n)
            except BaseException as exc:  # noqa: BLE001
                errors.append(exc)
                return

    th = threading.Thread(target=reader)
    th.start()
    try:
        for i in range(300):  # crosses a 256-ping chunk boundary
            p = oculus_pings[i % 3]
            sink.write(p.replace(time_ns=p.time_ns + i), prods[i % 3])
            time.sleep(0.003)
            if i % 75 == 74:  # let the reader see this stage (it reads while the next ones are written)
                k, t = len(seen), time.monotonic()
                while len(seen) == k and not errors and time.monotonic() - t < 10:
                    time.sleep(0.01)
    finally:
        sink.close()
        stop.set()
        th.join()
    assert not errors, errors[0]
    assert len(seen) >= 4 and seen == sorted(seen) and seen[-1] > seen[0]  # it grew while read
    assert load_products(path).sizes["ping_time"] == 300


# ---------------------------------------------------------------------------- CLI
def test_cli_ranges_to_stdout_parse_with_pandas(aris_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import pandas as pd

    from sonarmap.cli import main
    from sonarmap.ranges.csv_rows import CSV_HEADER

    assert main(["live", str(aris_file), "--replay", "--rate", "30", "--ranges", "-", "--queue", "8"]) == 0
    cap = capsys.readouterr()
    df = pd.read_csv(io.StringIO(cap.out), parse_dates=["time"])
    assert tuple(df.columns) == CSV_HEADER and len(df) == 6 * 48
    assert df["ping"].nunique() == 6 and "live: 6 pings" in cap.err
    assert main(["live", str(aris_file), "--replay", "--rate", "30", "--ranges", "-", "--format", "jsonl",
                 "--queue", "8", "-q"]) == 0
    cap = capsys.readouterr()
    js = pd.read_json(io.StringIO(cap.out), lines=True)
    assert len(js) == 6 and len(js["range_m"][0]) == 48 and cap.err == ""
    assert all(json.loads(line)["time_ns"] > 0 for line in cap.out.splitlines())


@pytest.mark.slow  # over a second in the fast subset
def test_cli_ranges_to_a_bag_replay_with_the_pings_stamps(aris_file: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    import pandas as pd
    from rosbags.highlevel import AnyReader

    from sonarmap.cli import main

    for name in ("r.bag", "r2"):  # ROS 1 file, ROS 2 directory
        bag = tmp_path / name
        csv_path = tmp_path / f"{name}.csv"
        assert main(["live", str(aris_file), "--replay", "--rate", "30", "--queue", "8", "--bag", str(bag),
                     "--ranges", str(csv_path), "-q"]) == 0
        df = pd.read_csv(csv_path)
        with AnyReader([bag]) as reader:
            msgs = [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
            assert {c.msgtype for c in reader.connections} == {"marine_acoustic_msgs/msg/SonarRanges"}
        assert len(msgs) == 6 == df["ping"].nunique()
        for (t, m), (_, rows) in zip(msgs, df.groupby("ping", sort=False)):
            assert t == int(rows["time_ns"].iloc[0]) == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            assert np.allclose(m.ranges, rows["range_m"].to_numpy(np.float32), equal_nan=True)
        # an existing bag is replaced only with --overwrite
        assert main(["live", str(aris_file), "--replay", "--rate", "50", "--bag", str(bag), "-q"]) == 1
        assert "--overwrite" in capsys.readouterr().err
        assert main(["live", str(aris_file), "--replay", "--rate", "50", "--bag", str(bag), "-q", "--overwrite"]) == 0


@pytest.mark.parametrize("args", [
    ["--replay", "--queue", "0"],
    ["--replay", "--format", "xml"],
    ["--follow", "--rate", "5"],
    [],
    ["--replay", "--oculus-range", "5"],  # sonar settings go to a live Oculus, not to a file
    ["--replay", "--oculus-frequency", "medium"],
])
def test_cli_bad_options_exit_2(args: list[str], aris_file: Path, tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main

    assert main(["live", str(aris_file), *args, "-o", str(tmp_path / "x.zarr")]) == 2
    assert "Invalid value" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_cli_existing_store_needs_overwrite(aris_file: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main

    (tmp_path / "x.zarr").mkdir()
    assert main(["live", str(aris_file), "--replay", "--rate", "50", "-o", str(tmp_path / "x.zarr"), "-q"]) == 1
    assert "--overwrite" in capsys.readouterr().err


@pytest.mark.slow
def test_sigint_leaves_a_valid_store(raw_capture: Path, tmp_path: Path) -> None:
    out = tmp_path / "int.zarr"
    with ReplayServer(raw_capture, rate_hz=10) as srv:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        proc = subprocess.Popen([sys.executable, "-m", "sonarmap", "live", srv.url, "-o", str(out),
                                 "--flush-every", "3", "--bag", str(tmp_path / "int.bag")],
                                stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        try:
            t0 = time.monotonic()
            while time.monotonic() - t0 < 30:  # until the store holds a few pings
                try:
                    if open_products(out).sizes["ping_time"] >= 6:
                        break
                except Exception:  # noqa: BLE001 - not created yet
                    pass
                time.sleep(0.05)
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, err
    line = next(ln for ln in err.splitlines() if ln.startswith("live: "))
    n = int(line.split()[1])
    assert "stopped by interrupt" in line and n >= 6
    ds = load_products(out)
    assert ds.sizes["ping_time"] == n and ds.attrs["live_status"] == "complete"
    # the bag is finished on Ctrl-C too: one SonarRanges per processed ping
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "int.bag"]) as reader:
        assert sum(1 for _ in reader.messages()) == n


def test_sigint_before_the_first_ping_writes_no_store_and_says_so(
    aris_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    """Ctrl-C while the run is still setting up (warming the pipeline): the same clean stop as a
    later one - exit 0, the summary line - with no store (nothing arrived to describe the sonar)."""
    import sonarmap.live
    from sonarmap.cli import main

    monkeypatch.setattr(sonarmap.live, "warm_pipeline", lambda *a, **k: signal.raise_signal(signal.SIGINT))
    out = tmp_path / "none.zarr"
    assert main(["live", str(aris_file), "--replay", "--rate", "30", "-o", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "0 pings" in err[0] and "stopped by interrupt" in err[0], err
    assert err[0].endswith(f"no ping arrived, so {out} was not written")
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("kind", ["raw", "log-v1"])
def test_follow_oculus_recordings(kind: str, raw_capture: Path, tmp_path: Path) -> None:
    from oculus_writer import write_log_v1

    from sonarmap.live.server import read_capture_messages

    msgs = read_capture_messages(raw_capture)
    full = tmp_path / "full.bin"
    if kind == "raw":
        full.write_bytes(b"".join(msgs))
    else:
        write_log_v1(full, msgs, [1_700_000_000.0 + 0.1 * i for i in range(len(msgs))])
    data = full.read_bytes()
    growing = tmp_path / f"growing.{'raw' if kind == 'raw' else 'oculus'}"

    def write() -> None:  # arbitrary pieces: messages / log items arrive in parts
        with open(growing, "wb") as fh:
            for a in range(0, len(data), 40_000):
                fh.write(data[a : a + 40_000])
                fh.flush()
                time.sleep(0.02)

    th = threading.Thread(target=write)
    th.start()
    col = Collect()
    try:
        stats = run_live(FollowSource(growing, idle_timeout_s=0.5), sinks=[col], queue_size=8)
    finally:
        th.join()
    assert stats.count == 3 and stats.drops == 0
    assert col.sources == [f"{growing}#{i}" for i in range(3)]


@pytest.mark.slow
def test_server_module_command_line(raw_capture: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "sonarmap.live.server", str(raw_capture), "--rate", "20",
                             "--port", "0", "--count", "5"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("listening on 127.0.0.1:"), line
        col = Collect()
        stats = run_live(OculusTcpSource("127.0.0.1", int(line.rsplit(":", 1)[1])), sinks=[col], max_pings=5,
                         queue_size=8, duration_s=20)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert stats.count == 5 and col.ids == [0, 1, 2, 3, 4]
    assert proc.returncode == 0 and "sent 5 messages" in err and "Warning" not in err, err


def test_store_skips_pings_of_another_geometry(aris_pings: list, oculus_pings: list, tmp_path: Path) -> None:
    from sonarmap.pipeline import process_ping

    sink = StoreSink(tmp_path / "g.zarr", config=None)
    sink.write(aris_pings[0], process_ping(aris_pings[0]))
    with pytest.warns(UserWarning, match="geometry"):
        sink.write(oculus_pings[0], process_ping(oculus_pings[0]))
    sink.write(aris_pings[1], process_ping(aris_pings[1]))
    sink.close()
    assert sink.n_skipped == 1 and load_products(tmp_path / "g.zarr").sizes["ping_time"] == 2


def test_store_is_created_in_the_writer_thread(aris_pings: list, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The first write only starts the store (its creation, ~0.25 s of zarr metadata, runs in the
    writer thread); a creation error comes back on close, and the lock is released."""
    import sonarmap.survey
    from sonarmap.errors import DataFormatError
    from sonarmap.pipeline import process_ping

    started = threading.Event()
    release = threading.Event()

    def slow_failing_create(*args: Any, **kwargs: Any) -> None:
        started.set()
        release.wait(5.0)
        raise DataFormatError("no space left on device", tmp_path / "c.zarr")

    monkeypatch.setattr(sonarmap.survey, "create_product_store", slow_failing_create)
    sink = StoreSink(tmp_path / "c.zarr", config=None, flush_every=1)
    products = process_ping(aris_pings[0])
    sink.write(aris_pings[0], products)  # returns while the store is still being created
    assert started.wait(5.0) and sink.n_written == 0
    sink.write(aris_pings[0], products)  # flushed rows wait in the queue
    release.set()
    with pytest.raises(DataFormatError, match="no space left"):
        sink.close()
    StoreSink(tmp_path / "c.zarr", config=None).close()  # the lock was released


def test_cli_sends_the_oculus_settings_in_the_fire_message(raw_capture: Path, tmp_path: Path) -> None:
    """--oculus-range / --oculus-gain / --oculus-frequency / --oculus-ping-rate / --no-gain-assist
    reach the sonar; by default gain assist is on (flags 0x19, as in the shared capture)."""
    from sonarmap.cli import main
    from sonarmap.live.protocol import FLAG_GAIN_ASSIST

    with ReplayServer(raw_capture, rate_hz=20, count=4) as srv:
        assert main(["live", srv.url, "--max-pings", "2", "-q", "--oculus-range", "5", "--oculus-gain", "30",
                     "--oculus-frequency", "low", "--oculus-ping-rate", "normal", "--no-gain-assist"]) == 0
        fire = srv.fire
    assert fire is not None
    assert (fire.range_m, fire.gain_percent, fire.master_mode, fire.ping_rate) == (5.0, 30.0, 1, 0)
    assert not fire.flags & FLAG_GAIN_ASSIST
    with ReplayServer(raw_capture, rate_hz=20, count=4) as srv:
        assert main(["live", srv.url, "--max-pings", "2", "-q"]) == 0
        assert srv.fire is not None and srv.fire.flags == 0x19 and srv.fire.range_m == 2.0
    with ReplayServer(raw_capture, rate_hz=20, count=4) as srv:
        assert main(["live", srv.url, "--max-pings", "2", "-q", "--oculus-gain", "150"]) == 2


def _grow_sqlite_bag(src_db: Path, dst_dir: Path, delay_s: float, start_s: float = 0.1) -> threading.Thread:
    """Copy a finished ROS 2 bag's storage into ``dst_dir`` row by row, as a recorder writes it
    (the schema and topics first, then one committed message every ``delay_s``; no metadata.yaml)."""
    import sqlite3

    def run() -> None:
        s = sqlite3.connect(src_db)
        time.sleep(start_s)
        d = sqlite3.connect(dst_dir / "rec_0.db3")
        for (sql,) in s.execute("SELECT sql FROM sqlite_master WHERE sql IS NOT NULL"):
            d.execute(sql)
        for row in s.execute("SELECT * FROM topics"):
            d.execute(f"INSERT INTO topics VALUES ({','.join('?' * len(row))})", row)
        d.commit()
        for row in s.execute("SELECT id, topic_id, timestamp, data FROM messages ORDER BY id"):
            d.execute("INSERT INTO messages VALUES (?, ?, ?, ?)", row)
            d.commit()
            time.sleep(delay_s)
        d.close()
        s.close()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


@pytest.mark.slow
def test_follow_a_ros2_bag_while_it_is_recorded(aris_pings: list, tmp_path: Path) -> None:
    from sonarmap.io import read_pings
    from sonarmap.io.rosbag import write_bag
    from sonarmap.live.sources import FollowSource

    full = tmp_path / "full"
    write_bag(aris_pings, full, version=2)
    rec = tmp_path / "rec"
    rec.mkdir()
    th = _grow_sqlite_bag(next(full.glob("*.db3")), rec, delay_s=0.15)
    src = FollowSource(rec, idle_timeout_s=1.0, poll_s=0.01)
    got, arrival = [], []
    t0 = time.monotonic()
    for ping in src:
        got.append(ping)
        arrival.append(time.monotonic() - t0)
    th.join()
    ref = list(read_pings(full))
    assert len(got) == len(ref) == 6 and src.format == "rosbag2-sqlite3"
    for a, b in zip(got, ref):
        assert np.array_equal(a.image, b.image) and a.time_ns == b.time_ns
        assert np.array_equal(a.geometry.range_m, b.geometry.range_m)  # the exact-geometry side channel
    # each ping is yielded as its row is committed (0.15 s apart), not at the end (the median gap:
    # a busy machine may delay one poll past two commits)
    assert np.median(np.diff(arrival)) > 0.08 and arrival[-1] - arrival[0] > 0.5


def test_follow_a_bag_without_a_sonar_topic_is_an_error(tmp_path: Path) -> None:
    import sqlite3

    from sonarmap.errors import DataFormatError
    from sonarmap.live.sources import FollowSource

    rec = tmp_path / "rec"
    rec.mkdir()
    d = sqlite3.connect(rec / "rec_0.db3")
    d.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT, type TEXT, serialization_format TEXT)")
    d.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER, timestamp INTEGER, data BLOB)")
    d.execute("INSERT INTO topics VALUES (1, '/imu', 'sensor_msgs/msg/Imu', 'cdr')")
    d.commit()
    d.close()
    with pytest.raises(DataFormatError, match=r"no sonar topic to follow.*/imu \(sensor_msgs/msg/Imu\)"):
        list(FollowSource(rec, idle_timeout_s=0.2, wait_s=0.3))


def test_summary_says_one_ping_not_one_pings() -> None:
    from sonarmap.live import LiveStats

    def stats(n: int) -> LiveStats:
        return LiveStats(count=n, received=n, drops=0, unprocessed=0, flagged=0, malformed=0, reconnects=0,
                         latency_p50_ms=3.0, latency_p99_ms=3.0, latency_max_ms=3.0, process_p50_ms=3.0,
                         elapsed_s=1.0, stopped_by="interrupt")

    assert stats(1).summary().startswith("1 ping in 1.0 s") and stats(2).summary().startswith("2 pings in ")
