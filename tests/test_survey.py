"""Survey batch runs: chunking, executors (serial, processes, dask LocalCluster), resume, safety."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import types
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


def _standin(ping, config, *, keep_labels=False):  # noqa: ANN001, ANN202
    """Stand-in for sonarmap.pipeline.process_ping when that module is not there yet."""
    img = ping.image
    thr = float(img.mean() + 2 * img.std())
    lab = img > thr
    hit = lab.any(axis=0)
    b = np.where(hit, lab.argmax(axis=0), -1)
    cols = np.arange(img.shape[1])
    ranges = types.SimpleNamespace(
        range_m=np.where(b >= 0, ping.geometry.range_m[np.clip(b, 0, None)], np.nan),
        bin=b,
        intensity=np.where(b >= 0, img[np.clip(b, 0, None), cols], np.nan),
        confidence=hit.astype(float),
        azimuth_rad=ping.geometry.azimuth_rad,
        time_ns=ping.time_ns,
        source=ping.source,
    )
    return types.SimpleNamespace(
        time_ns=ping.time_ns, source=ping.source,
        fit={"weights": [0.9, 0.1], "params": [[float(img.mean()), 1.0], [thr, 2.0]]},
        kld=float(img.std()), flags=("dim",) if img.mean() < 0.02 else (), ranges=ranges,
        labels=lab if keep_labels else None, pd=0.9, pfa=0.01,
    )


def _has_pipeline() -> bool:
    try:
        import sonarmap.pipeline  # noqa: F401
    except ModuleNotFoundError:
        return False
    return True


#: The real pipeline when it exists (None = default), else the stand-in.
PING_FUNCTION = None if _has_pipeline() else _standin


def _slow(ping, config, *, keep_labels=False):  # noqa: ANN001, ANN202
    """The per-ping function, slowed so a run can be interrupted part-way."""
    time.sleep(0.02)
    fn = PING_FUNCTION
    if fn is None:
        from sonarmap.pipeline import process_ping as fn
    return fn(ping, config, keep_labels=keep_labels)


@pytest.fixture(scope="module")
def survey_dir(tmp_path_factory: pytest.TempPathFactory, test_ping_paths: list[Path],
               background_paths: list[Path]) -> Path:
    """A 40-ping survey: links to the real test and background pings under new time stamps."""
    srcs = [p for pair in zip(test_ping_paths, background_paths[:10], strict=True) for p in pair]
    return replicate_pings(srcs, N_PINGS, tmp_path_factory.mktemp("survey") / "pings")


@pytest.fixture(scope="module")
def serial_store(survey_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("serial") / "s.zarr"
    process_survey([survey_dir], out, workers=0, chunk_size=8, ping_function=PING_FUNCTION)
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


def test_local_processes_match_serial(serial_store: Path, survey_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "p.zarr"
    res = process_survey([survey_dir], out, workers=2, chunk_size=8, ping_function=PING_FUNCTION)
    assert res.executor == "processes:2" and res.n_pings == N_PINGS and res.chunks_run == 5
    assert_same_dataset(serial_store, out)


def test_dask_cluster_matches_serial(cluster, serial_store: Path, survey_dir: Path, tmp_path: Path) -> None:  # noqa: ANN001
    out = tmp_path / "d.zarr"
    res = process_survey([survey_dir], out, client=cluster, chunk_size=8, ping_function=PING_FUNCTION)
    assert res.executor.startswith("dask:")
    assert_same_dataset(serial_store, out)
    # The same through a scheduler address (what --scheduler does).
    out2 = tmp_path / "d2.zarr"
    process_survey([survey_dir], out2, scheduler=cluster.scheduler.address, chunk_size=8,
                   ping_function=PING_FUNCTION)
    assert_same_dataset(serial_store, out2)


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
        process_survey([survey_dir], out, workers=0, chunk_size=8, ping_function=PING_FUNCTION,
                       progress=stop_after_two_chunks)
    st = survey_status(out)
    assert st["done"] == 2 and not st["complete"]
    res = process_survey([survey_dir], out, workers=2, chunk_size=8, ping_function=PING_FUNCTION)
    assert res.chunks_skipped == 2 and res.chunks_run == 3
    assert_same_dataset(serial_store, out)


def test_existing_output_is_never_overwritten_silently(
    serial_store: Path, survey_dir: Path, tmp_path: Path,
) -> None:
    # A completed run of the same command is a no-op.
    again = process_survey([survey_dir], serial_store, workers=0, chunk_size=8, ping_function=PING_FUNCTION)
    assert again.chunks_run == 0 and again.chunks_skipped == 5
    # Different options -> refused, store untouched.
    before = (serial_store / "zarr.json").read_bytes()
    with pytest.raises(SurveyExistsError, match="overwrite"):
        process_survey([survey_dir], serial_store, workers=0, chunk_size=4, ping_function=PING_FUNCTION)
    assert (serial_store / "zarr.json").read_bytes() == before
    # Something that is not a survey -> refused; with overwrite -> replaced.
    other = tmp_path / "o.zarr"
    other.mkdir()
    (other / "keep.txt").write_text("precious")
    with pytest.raises(SurveyExistsError, match="not a sonarmap survey"):
        process_survey([survey_dir], other, workers=0, chunk_size=8, ping_function=PING_FUNCTION)
    assert (other / "keep.txt").exists()
    process_survey([survey_dir], other, workers=0, chunk_size=8, ping_function=PING_FUNCTION, overwrite=True)
    assert not (other / "keep.txt").exists()
    assert_same_dataset(serial_store, other)


# ---------------------------------------------------------------------------- CLI
def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "sonarmap", *args]


@pytest.mark.skipif(PING_FUNCTION is not None, reason="sonarmap.pipeline not available yet")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_cli_kill_and_rerun_gives_identical_dataset(
    sig: int, test_ping_paths: list[Path], tmp_path: Path,
) -> None:
    pings = replicate_pings(test_ping_paths, 96, tmp_path / "pings")
    args = ["process", str(pings), "--chunk-size", "4", "--workers", "1", "--quiet"]
    clean = tmp_path / "clean.zarr"
    r = subprocess.run(_cli(*args, "-o", str(clean)), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "killed.zarr"
    # SIGINT must reach Python's handler even if this test runs with SIGINT ignored (background job).
    proc = subprocess.Popen(_cli(*args, "-o", str(out)), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    marks = out / ".sonarmap" / "chunks"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        if marks.is_dir() and len(os.listdir(marks)) >= 2:
            break
        time.sleep(0.002)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == (130 if sig == signal.SIGINT else -signal.SIGKILL), err
    st = survey_status(out)
    assert 0 < st["done"] < st["n_chunks"] and not st["complete"], st
    r = subprocess.run(_cli(*args, "-o", str(out)), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert survey_status(out)["complete"]
    assert_same_dataset(clean, out)


@pytest.mark.skipif(PING_FUNCTION is not None, reason="sonarmap.pipeline not available yet")
def test_cli_summary_quiet_and_refusal(survey_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "c.zarr"
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(out), "-k", "16"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"{N_PINGS} pings" in r.stdout and "flagged" in r.stdout and "pings/s" in r.stdout
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(out), "-k", "8", "--quiet"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "--overwrite" in r.stderr and r.stdout == ""
    bad = tmp_path / "bad.toml"
    bad.write_text("this is = = not toml\n")
    r = subprocess.run(_cli("process", str(survey_dir), "-o", str(tmp_path / "x.zarr"), "-c", str(bad)),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "bad.toml" in r.stderr
    assert not (tmp_path / "x.zarr").exists()
