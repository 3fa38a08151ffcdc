"""Survey batch runs: chunking, executors (serial, processes, dask LocalCluster), resume, safety."""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.survey import (
    SurveyExistsError,
    open_products,
    plan_survey,
    process_survey,
    replicate_pings,
    survey_status,
)

N_PINGS = 40


def _slow(ping, config, *, keep_labels=False):  # noqa: ANN001, ANN202
    """The per-ping function, slowed so a run can be interrupted part-way."""
    from sonarmap.pipeline import process_ping

    time.sleep(0.02)
    return process_ping(ping, config, keep_labels=keep_labels)


@pytest.fixture(scope="module")
def survey_dir(tmp_path_factory: pytest.TempPathFactory, test_ping_paths: list[Path],
               background_paths: list[Path]) -> Path:
    """A 40-ping survey: links to the real test and background pings under new time stamps."""
    srcs = [p for pair in zip(test_ping_paths, background_paths[:10], strict=True) for p in pair]
    return replicate_pings(srcs, N_PINGS, tmp_path_factory.mktemp("survey") / "pings")


@pytest.fixture(scope="module")
def serial_store(survey_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("serial") / "s.zarr"
    process_survey([survey_dir], out, workers=0, chunk_size=8)
    return out


@pytest.fixture(scope="module")
def cluster():  # noqa: ANN201
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
        dashboard_address=None, silence_logs=40,
    ) as cl, distributed.Client(cl) as client:
        yield client


def assert_same_dataset(a: Path, b: Path) -> None:
    """Every variable equal exactly (NaN == NaN), same dims/attrs; provenance equal."""
    da, db = open_products(a).load(), open_products(b).load()
    assert sorted(da.variables) == sorted(db.variables)
    for name in da.variables:
        x, y = da[name], db[name]
        assert x.dims == y.dims, name
        assert x.attrs == y.attrs, name
        xv, yv = x.values, y.values
        if xv.dtype.kind == "f":
            np.testing.assert_array_equal(xv, yv, err_msg=name)
        else:
            assert xv.tolist() == yv.tolist(), name
    assert da.attrs == db.attrs


def assert_same_products(a: Path, b: Path) -> None:
    """Every product variable equal exactly (the stores may differ in chunking/provenance)."""
    da, db = open_products(a).load(), open_products(b).load()
    assert sorted(da.variables) == sorted(db.variables)
    for name in da.variables:
        xv, yv = da[name].values, db[name].values
        if xv.dtype.kind == "f":
            np.testing.assert_array_equal(xv, yv, err_msg=name)
        else:
            assert xv.tolist() == yv.tolist(), name


def test_plan_covers_every_ping_once_in_time_order(survey_dir: Path) -> None:
    plan = plan_survey([survey_dir], chunk_size=7)
    assert plan.n_pings == N_PINGS and plan.n_chunks == 6
    chunks = plan.chunks()
    assert [c.start for c in chunks] == [0, 7, 14, 21, 28, 35]
    assert chunks[-1].stop == N_PINGS and chunks[-1].n_pings == 5
    paths = [item[0] for c in chunks for item in c.items]
    assert len(paths) == N_PINGS and paths == sorted(paths)  # µs stamps of equal width sort by time
    with pytest.raises(InputError, match="chunk_size"):
        plan_survey([survey_dir], chunk_size=0)


def test_serial_store_holds_all_products(serial_store: Path, survey_dir: Path) -> None:
    ds = open_products(serial_store)
    assert ds.sizes["ping_time"] == N_PINGS
    assert ds.sizes["beam"] == 96
    times = ds["ping_time"].values
    assert np.all(np.diff(times.astype(np.int64)) == 100_000_000)
    assert ds["range"].dims == ("ping_time", "beam")
    assert ds["range_confidence"].dims == ("ping_time", "beam")
    assert ds["mixture_weight"].dims == ("ping_time", "component")
    assert "labels" not in ds  # only on request
    src = [Path(s).name for s in ds["source"].values]
    assert src == sorted(p.name for p in survey_dir.glob("*_raw.png"))
    # Every ping filled: finite KLD and a range (or an explicit -1 bin) for each beam.
    assert np.isfinite(ds["kld"].values).all()
    rb = ds["range_bin"].values
    assert ((rb >= -1) & (rb < 512)).all() and (rb >= 0).any()
    assert np.isnan(ds["range"].values[rb < 0]).all()
    # Provenance: version and configuration.
    assert ds.attrs["sonarmap_version"]
    assert "pipeline_config" in ds.attrs
    st = survey_status(serial_store)
    assert st["complete"] and st["done"] == st["n_chunks"] == 5


@pytest.mark.slow
def test_local_processes_match_serial(serial_store: Path, survey_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "p.zarr"
    res = process_survey([survey_dir], out, workers=2, chunk_size=8)
    assert res.executor == "processes:2" and res.n_pings == N_PINGS and res.chunks_run == 5
    assert_same_dataset(serial_store, out)


@pytest.mark.slow
def test_dask_cluster_matches_serial(cluster, serial_store: Path, survey_dir: Path, tmp_path: Path) -> None:  # noqa: ANN001
    out = tmp_path / "d.zarr"
    res = process_survey([survey_dir], out, client=cluster, chunk_size=8)
    assert res.executor.startswith("dask:")
    assert_same_dataset(serial_store, out)
    # The same through a scheduler address (what --scheduler does).
    out2 = tmp_path / "d2.zarr"
    process_survey([survey_dir], out2, scheduler=cluster.scheduler.address, chunk_size=8)
    assert_same_dataset(serial_store, out2)


@pytest.mark.slow
def test_dask_worker_killed_mid_run_loses_no_ping(
    cluster, serial_store: Path, survey_dir: Path, tmp_path: Path,  # noqa: ANN001
) -> None:
    out = tmp_path / "k.zarr"
    pids = list(cluster.run(os.getpid).values())
    assert len(pids) == 2
    killed: list[int] = []

    def killer() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            marks = out / ".sonarmap" / "chunks"
            if marks.is_dir() and any(f.suffix == ".done" for f in marks.iterdir()):
                st = survey_status(out)
                if st["done"] < st["n_chunks"]:
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(st["done"])
                return
            time.sleep(0.005)

    th = threading.Thread(target=killer)
    th.start()
    res = process_survey([survey_dir], out, client=cluster, chunk_size=4, ping_function=_slow)
    th.join()
    assert killed, "the worker was not killed part-way (run finished too fast)"
    assert res.n_pings == N_PINGS
    st = survey_status(out)
    assert st["complete"] and st["done"] == st["n_chunks"] == 10
    # Same products as the serial run (the slow wrapper does not change values).
    a, b = open_products(serial_store).load(), open_products(out).load()
    for name in ("kld", "range", "range_bin", "mixture_weight", "mixture_param", "source", "flags"):
        if a[name].dtype.kind == "f":
            np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
        else:
            assert a[name].values.tolist() == b[name].values.tolist(), name
    cluster.wait_for_workers(2, timeout=60)


@pytest.mark.slow
def test_interrupted_run_resumes_to_identical_output(
    serial_store: Path, survey_dir: Path, tmp_path: Path,
) -> None:
    out = tmp_path / "r.zarr"
    calls = []

    def stop_after_two_chunks(done: int, total: int) -> None:
        calls.append(done)
        if len(calls) == 3:  # start + two chunks stored
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        process_survey([survey_dir], out, workers=0, chunk_size=8,
                       progress=stop_after_two_chunks)
    st = survey_status(out)
    assert st["done"] == 2 and not st["complete"]
    res = process_survey([survey_dir], out, workers=0, chunk_size=8)
    assert res.chunks_skipped == 2 and res.chunks_run == 3
    assert_same_dataset(serial_store, out)


@pytest.mark.slow
def test_existing_output_is_never_overwritten_silently(
    serial_store: Path, survey_dir: Path, tmp_path: Path,
) -> None:
    # A completed run of the same command is a no-op.
    again = process_survey([survey_dir], serial_store, workers=0, chunk_size=8)
    assert again.chunks_run == 0 and again.chunks_skipped == 5
    # Different options -> refused, store untouched.
    before = (serial_store / "zarr.json").read_bytes()
    with pytest.raises(SurveyExistsError, match="overwrite"):
        process_survey([survey_dir], serial_store, workers=0, chunk_size=4)
    assert (serial_store / "zarr.json").read_bytes() == before
    # Something that is not a survey -> refused; with overwrite -> replaced.
    other = tmp_path / "o.zarr"
    other.mkdir()
    (other / "keep.txt").write_text("precious")
    with pytest.raises(SurveyExistsError, match="not a sonarmap survey"):
        process_survey([survey_dir], other, workers=0, chunk_size=8)
    assert (other / "keep.txt").exists()
    process_survey([survey_dir], other, workers=0, chunk_size=8, overwrite=True)
    assert not (other / "keep.txt").exists()
    assert_same_dataset(serial_store, other)


@pytest.mark.slow
def test_labels_on_request_and_points_with_poses(
    serial_store: Path, survey_dir: Path, tmp_path: Path,
) -> None:
    from sonarmap.mapping import Trajectory, read_point_cloud, write_trajectory_csv

    t = open_products(serial_store)["ping_time"].values.astype(np.int64)
    # The vehicle moves north at 1 m/s, level; the sonar (= body) looks forward.
    tt = np.array([t[0] - 10**9, t[-1] + 10**9])
    traj = Trajectory(tt, np.array([[0.0, 0, 0], [(tt[1] - tt[0]) * 1e-9, 0, 0]]), np.array([[0, 0, 0, 1.0]] * 2))
    poses = tmp_path / "poses.csv"
    write_trajectory_csv(traj, poses)
    out = tmp_path / "lp.zarr"
    res = process_survey([survey_dir], out, workers=0, chunk_size=8, keep_labels=True, poses=poses)
    ds = open_products(out).load()
    assert ds["labels"].dims == ("ping_time", "range_sample", "beam")
    assert ds["labels"].shape == (N_PINGS, 512, 96) and ds["labels"].dtype == np.uint8
    # Stored labels are the pipeline's, ping by ping and in order.
    from sonarmap.io import read_ping
    from sonarmap.pipeline import PipelineConfig, process_ping

    for i in (0, 17, N_PINGS - 1):
        ping = read_ping(str(ds["source"].values[i]))
        expect = process_ping(ping, PipelineConfig(), keep_labels=True).labels
        np.testing.assert_array_equal(ds["labels"].values[i], expect)
    assert ds["labels"].values.any()
    # One point per return, placed at range r along the beam from the interpolated position.
    r = ds["range"].values
    n_ret = int(np.isfinite(r).sum())
    assert res.n_points == n_ret == ds.sizes["point"] > 0
    xyz = ds["point_xyz"].values
    pt = ds["point_time"].values.astype(np.int64)
    x0 = (pt - tt[0]) * 1e-9
    np.testing.assert_allclose(np.hypot(xyz[:, 0] - x0, xyz[:, 1]), r[np.isfinite(r)], rtol=1e-5)
    assert res.points_path == out.with_suffix(".ply")
    assert len(read_point_cloud(res.points_path)) == n_ret
    # Products other than labels/points are those of the plain run.
    base = open_products(serial_store).load()
    np.testing.assert_array_equal(ds["range"].values, base["range"].values)


# ---------------------------------------------------------------------------- CLI
def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "sonarmap", *args]


KILL_ARGS = ("--chunk-size", "4", "--workers", "1", "--quiet")


@pytest.fixture(scope="module")
def kill_survey(tmp_path_factory: pytest.TempPathFactory, test_ping_paths: list[Path]) -> tuple[Path, Path]:
    """48 pings and their clean, uninterrupted `sonarmap process` output."""
    d = tmp_path_factory.mktemp("kill")
    pings = replicate_pings(test_ping_paths, 48, d / "pings")
    clean = d / "clean.zarr"
    r = subprocess.run(_cli("process", str(pings), *KILL_ARGS, "-o", str(clean)),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return pings, clean


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
@pytest.mark.slow
def test_cli_kill_and_rerun_gives_identical_dataset(
    sig: int, kill_survey: tuple[Path, Path], tmp_path: Path,
) -> None:
    pings, clean = kill_survey
    out = tmp_path / "killed.zarr"
    cmd = _cli("process", str(pings), *KILL_ARGS, "-o", str(out))
    # SIGINT must reach Python's handler even if this test runs with SIGINT ignored (background job).
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    marks = out / ".sonarmap" / "chunks"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if marks.is_dir() and sum(f.endswith(".done") for f in os.listdir(marks)) >= 2:
            break
        time.sleep(0.002)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    assert proc.returncode == (130 if sig == signal.SIGINT else -signal.SIGKILL)
    st = survey_status(out)
    assert 0 < st["done"] < st["n_chunks"] and not st["complete"], st
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert survey_status(out)["complete"]
    assert_same_dataset(clean, out)


@pytest.mark.slow
def test_cli_summary_quiet_and_refusal(survey_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "c.zarr"
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(out), "-k", "16"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""  # the summary is a message: stderr
    summary = [ln for ln in r.stderr.splitlines() if "flagged fits" in ln or "pings flagged" in ln]
    assert len(summary) == 2 and f"{N_PINGS} pings" in summary[0] and "[processes:" in summary[0]
    assert "of 40 pings flagged" in summary[1]
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(out), "-k", "8", "--quiet"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "--overwrite" in r.stderr and r.stdout == ""
    bad = tmp_path / "bad.toml"
    bad.write_text("this is = = not toml\n")
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(tmp_path / "x.zarr"), "-c", str(bad)),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "bad.toml" in r.stderr
    assert not (tmp_path / "x.zarr").exists()


@pytest.mark.slow
def test_cli_scheduler_option_runs_on_the_cluster(
    cluster, serial_store: Path, survey_dir: Path, tmp_path: Path,  # noqa: ANN001
) -> None:
    out = tmp_path / "cli-dask.zarr"
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(out), "-k", "8",
                            "--scheduler", cluster.scheduler.address),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"[dask:{cluster.scheduler.address}]" in r.stderr
    assert_same_dataset(serial_store, out)
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(tmp_path / "y.zarr"), "--workers", "2",
                            "--scheduler", cluster.scheduler.address), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--workers" in r.stderr


@pytest.mark.slow
def test_local_workers_store_their_own_chunks(
    serial_store: Path, survey_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Local workers write their chunk files themselves: the parent receives only a receipt per
    chunk (no products) and writes the marker; the dataset is the serial run's."""
    import sonarmap.survey.run as sv

    got: list[object] = []
    put = sv._Sink.put

    def spy(self, chunk, result):  # noqa: ANN001, ANN202
        got.append(result)
        return put(self, chunk, result)

    monkeypatch.setattr(sv._Sink, "put", spy)
    out = tmp_path / "w.zarr"
    process_survey([survey_dir], out, workers=2, chunk_size=8)
    # 5 chunks: 0-2 whole, 3 and 4 (the last one per worker) in two parts each to balance the
    # tail; the first 2 * workers jobs started before the store existed.  All those products
    # came back here to be stored: chunks 0, 1, 2 and 3, 4 (assembled from their parts).
    assert len(got) == 5 and all(isinstance(r, dict) and len(r["ping_time"]) == 8 for r in got)
    assert_same_dataset(serial_store, out)
    # With more chunks, the workers store the rest themselves and send a receipt only.
    got.clear()
    out4 = tmp_path / "w4.zarr"
    process_survey([survey_dir], out4, workers=2, chunk_size=4)  # 10 chunks, too small to split
    stored = sorted(r.index for r in got if isinstance(r, sv._Stored))
    assert len(got) == 10 and stored == [4, 5, 6, 7, 8, 9]
    assert_same_products(serial_store, out4)
    # Resumed runs have no store to create: every chunk is stored by its worker.
    shutil.rmtree(out4 / "range" / "c")
    for m in (out4 / ".sonarmap" / "chunks").iterdir():
        m.unlink()
    (out4 / ".sonarmap" / "complete").unlink()
    got.clear()
    process_survey([survey_dir], out4, workers=2, chunk_size=4)
    assert sorted(r.index for r in got if isinstance(r, sv._Stored)) == list(range(10))
    assert_same_products(serial_store, out4)
    assert not (out / ".sonarmap" / "tmp").exists()


@pytest.mark.slow
def test_resume_removes_temporaries_of_the_interrupted_run(
    serial_store: Path, survey_dir: Path, tmp_path: Path,
) -> None:
    out = tmp_path / "t.zarr"

    def stop(done: int, total: int) -> None:
        if done >= 16:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        process_survey([survey_dir], out, workers=0, chunk_size=8, progress=stop)
    leftover = out / ".sonarmap" / "tmp" / "12345-deadbeef"  # as a writer killed mid-write leaves
    leftover.parent.mkdir(exist_ok=True)
    leftover.write_bytes(b"partial")
    process_survey([survey_dir], out, workers=0, chunk_size=8)
    assert not leftover.exists() and not leftover.parent.exists()
    assert_same_dataset(serial_store, out)


@pytest.mark.slow
def test_pool_workers_start_with_a_warm_pipeline() -> None:
    """Every worker runs the pipeline once when it starts, before its first task."""
    from sonarmap.survey.executors import _is_warm, _ProcessPool

    pool = _ProcessPool(2, None)
    try:
        states = {pool.ex.submit(_is_warm).result(timeout=120) for _ in range(4)}
    finally:
        pool.close(True)
    assert states == {True}


def test_tail_parts_cover_the_last_chunks_and_give_their_products(survey_dir: Path) -> None:
    from sonarmap.survey import run_chunk
    from sonarmap.survey.plan import _resolve_config, _sub_chunk, _tail_parts
    from sonarmap.survey.executors import _concat_parts

    plan = plan_survey([survey_dir], chunk_size=12)  # chunks of 12, 12, 12, 4
    chunks = plan.chunks()
    assert [c.n_pings for c in chunks] == [12, 12, 12, 4]
    jobs = _tail_parts(chunks, 2)
    # The last 2 (= workers) chunks are split into 2 * workers parts of >= 4 pings: chunk 2 into
    # 3 parts, chunk 3 (4 pings) not at all; earlier chunks stay whole.
    assert [(c.index, None if p is None else (p.start, p.stop)) for c, p in jobs] == [
        (0, None), (1, None), (2, (24, 28)), (2, (28, 32)), (2, (32, 36)), (3, None),
    ]
    cfg = _resolve_config(None)
    c = chunks[2]
    whole = run_chunk(c, cfg)
    halves = _concat_parts([run_chunk(_sub_chunk(c, 0, 5), cfg), run_chunk(_sub_chunk(c, 5, 12), cfg)])
    assert sorted(whole) == sorted(halves)
    for name in whole:
        if whole[name].dtype.kind == "f":
            np.testing.assert_array_equal(whole[name], halves[name], err_msg=name)
        else:
            assert whole[name].tolist() == halves[name].tolist(), name
    assert [it[0] for it in _sub_chunk(c, 5, 12).items] == [it[0] for it in c.items[5:12]]


def test_water_column_with_per_ping_geometry_is_refused_before_any_work(data_dir: Path, tmp_path: Path) -> None:
    """A Kongsberg water-column recording (range window and beam angles change every ping) is
    refused when planned, with what to use instead - no store, no worker started."""
    import warnings

    out = tmp_path / "k.zarr"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the shared file's truncated last ping
        with pytest.raises(InputError, match="Kongsberg EM .all/.wcd water column .* `sonarmap ranges`"):
            process_survey([data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"], out, workers=2)
    assert not out.exists()


def test_summary_rate_of_a_short_run_is_not_zero(tmp_path):
    from sonarmap.survey.run import SurveyResult

    r = SurveyResult(output=tmp_path / "s.zarr", n_pings=6, n_flagged=0, n_chunks=1, chunks_run=1,
                     chunks_skipped=0, elapsed_s=13.1, executor="processes:1")
    assert "0.46 pings/s" in r.summary()
    assert "570 pings/s" in SurveyResult(output=tmp_path / "s.zarr", n_pings=42_000, n_flagged=0, n_chunks=1,
                                         chunks_run=1, chunks_skipped=0, elapsed_s=73.7,
                                         executor="processes:2").summary()


@pytest.mark.slow
def test_resume_computes_again_the_damaged_chunks_of_a_finished_store(
    serial_store: Path, survey_dir: Path, tmp_path: Path,
) -> None:
    from sonarmap.errors import DataFormatError, SonarmapWarning
    from sonarmap.survey import load_products

    out = tmp_path / "d.zarr"
    shutil.copytree(serial_store, out)
    (out / "range" / "c" / "2" / "0").write_bytes(os.urandom(100))  # overwritten with garbage
    (out / "flags" / "c" / "3").unlink()  # deleted
    with pytest.warns(SonarmapWarning, match=r"chunk 2 \(pings 16-23\) is damaged \(array 'range', chunk c/2/0: "
                                             r"checksum mismatch.*and 1 more chunk"):
        res = process_survey([survey_dir], out, workers=0, chunk_size=8)
    assert res.chunks_run == 2 and res.chunks_skipped == 3
    assert_same_dataset(serial_store, out)
    load_products(out)  # what `sonarmap report` reads: every chunk checked
    # A coordinate is written with the store: resuming cannot redo it, the error says how to recover.
    (out / "echo_range" / "c" / "1" / "0").write_bytes(b"garbage")
    with pytest.raises(DataFormatError, match=r"array 'echo_range', chunk c/1/0: checksum mismatch.*--overwrite"):
        process_survey([survey_dir], out, workers=0, chunk_size=8)


def test_summary_of_a_run_with_nothing_left_to_compute_gives_no_rate(tmp_path: Path) -> None:
    from sonarmap.survey import SurveyResult

    done = SurveyResult(output=tmp_path / "s.zarr", n_pings=116, n_flagged=0, n_chunks=4, chunks_run=0,
                        chunks_skipped=4, elapsed_s=0.7, executor="none")
    assert done.summary() == f"116 pings, 0 flagged fits, resumed (4/4 chunks already done) -> {tmp_path / 's.zarr'}"
    part = dataclasses.replace(done, chunks_run=1, chunks_skipped=3)
    assert ", 0.7 s, " in part.summary() and "pings/s [none], resumed (3/4 chunks already done)" in part.summary()
