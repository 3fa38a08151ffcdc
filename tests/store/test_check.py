"""Hardening of the survey stores: corrupt metadata, checksummed chunks, value checks, locks, temporaries.

Regression tests for the reproducers of the fuzzing run (a bad ``zarr.json``, a deleted
``geometry_index`` or ``ping_time``, ``sonarmap report`` on a corrupt store, bad float pixels,
times beyond int64, two writers, abandoned temporary files, disk full), a seeded test of 200
single-bit flips in chunk files, and a seeded mini-fuzz of metadata and chunk files.  Stores are a
few tiny pings written in ``tmp_path`` by the package's own writers (no real data copied).
"""

from __future__ import annotations

import errno
import gc
import json
import os
import re
import shutil
import subprocess
import sys
import time
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.geometry import SonarGeometry
from sonarmap.io import read_pings, zarrstore
from sonarmap.store import SurveyWriter, dataset_to_pings, open_survey, write_survey
from sonarmap.ping import Ping, Pose

T0 = 1_600_000_000_000_000_000


# ---------------------------------------------------------------------------- fixtures
def _geometry() -> SonarGeometry:
    return SonarGeometry.from_window(min_range_m=1.0, max_range_m=5.0, n_bins=8, n_beams=4, fov_rad=0.5,
                                     name="tiny")


def _pings(n: int = 4) -> list[Ping]:
    """Tiny pings with every kind of stored field: poses on some, int/float/bool metadata."""
    g = _geometry()
    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        pose = Pose(position_m=[i, 0.5, -1.0], orientation_xyzw=[0, 0, 0, 1]) if i % 2 else None
        out.append(Ping(rng.random((8, 4), dtype=np.float32), g, time_ns=T0 + i * 100_000_000, pose=pose,
                        source=f"sim#{i}", meta={"frame": i, "gain_db": 0.5 * i, "flip": bool(i % 2)}))
    return out


def fake_ping_function(ping: Ping, config: Any, *, keep_labels: bool = False) -> Any:
    """A cheap stand-in for the pipeline: products with every variable, from the image."""
    from sonarmap.ranges import BeamRanges

    img = ping.image
    n = img.shape[1]
    b = np.argmax(img, axis=0).astype(np.int64)
    b[0] = -1  # a beam without return
    rng = np.where(b >= 0, ping.geometry.range_m[np.maximum(b, 0)], np.nan)
    r = BeamRanges(range_m=rng, bin=b, intensity=np.where(b >= 0, img.max(axis=0), np.nan).astype(np.float32),
                   confidence=np.full(n, 0.5, np.float32), azimuth_rad=ping.geometry.azimuth_rad,
                   time_ns=ping.time_ns, source=ping.source, sigma_m=np.where(b >= 0, 0.01, np.nan))
    fit = {"weights": [0.25, 0.75], "params": [[1.0], [2.0, 0.5]], "component_names": ("spike", "gamma")}
    return types.SimpleNamespace(
        time_ns=ping.time_ns, source=ping.source, fit=fit, kld=float(img.mean()),
        flags=("kld",) if img.mean() > 0.55 else (), ranges=r, pd=0.9, pfa=0.01, background=None,
        labels=(img > 0.5).astype(np.uint8) if keep_labels else None,
    )


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A raw store (4 pings, chunks of 2), a one-chunk raw store and a product store (chunks of 2)."""
    from sonarmap.survey import process_survey

    d = tmp_path_factory.mktemp("seeds")
    raw = d / "raw.zarr"
    write_survey(_pings(), raw, chunk_pings=2)
    one = d / "one.zarr"
    write_survey(_pings(), one, chunk_pings=4)
    prod = d / "prod.zarr"
    process_survey([raw], prod, workers=0, chunk_size=2, ping_function=fake_ping_function)
    return {"raw": raw, "one": one, "prod": prod}


def _copy(src: Path, dst_dir: Path, name: str | None = None) -> Path:
    dst = dst_dir / (name or src.name)
    shutil.copytree(src, dst)
    return dst


def _read_all(store: Path) -> list[Ping]:
    return list(read_pings(store))


def _same_pings(a: list[Ping], b: list[Ping]) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if not (np.array_equal(x.image, y.image) and x.time_ns == y.time_ns and x.source == y.source
                and x.geometry == y.geometry and x.meta == y.meta
                and {k: type(v) for k, v in x.meta.items()} == {k: type(v) for k, v in y.meta.items()}):
            return False
        if (x.pose is None) != (y.pose is None):
            return False
        if x.pose is not None and not (np.array_equal(x.pose.position_m, y.pose.position_m)
                                       and np.array_equal(x.pose.orientation_xyzw, y.pose.orientation_xyzw)
                                       and x.pose.frame == y.pose.frame):
            return False
    return True


def _chunk_files(store: Path) -> list[Path]:
    return sorted(p for p in store.rglob("*") if p.is_file() and p.name != "zarr.json"
                  and ".sonarmap" not in p.relative_to(store).parts)


def _edit_json(path: Path, fn: Callable[[dict[str, Any]], None]) -> None:
    d = json.loads(path.read_text(encoding="utf-8"))
    fn(d)
    path.write_text(json.dumps(d), encoding="utf-8")


def _one_line_error(store: Path, exc: BaseException) -> str:
    msg = str(exc)
    assert isinstance(exc, DataFormatError), repr(exc)
    assert "\n" not in msg and str(store) in msg, msg
    return msg


# ---------------------------------------------------------------------------- metadata
BAD_JSON: dict[str, tuple[str, Callable[[Path], None]]] = {
    "root truncated": ("zarr.json", lambda p: p.write_bytes(p.read_bytes()[:30])),
    "root invalid UTF-8": ("zarr.json", lambda p: p.write_bytes(b"\xff\xfe" + p.read_bytes())),
    "root is a list": ("zarr.json", lambda p: p.write_text("[1, 2]")),
    "root empty": ("zarr.json", lambda p: p.write_bytes(b"")),
    "root attributes a list": ("zarr.json", lambda p: _edit_json(p, lambda d: d.update(attributes=[1]))),
    "root without node_type": ("zarr.json", lambda p: _edit_json(p, lambda d: d.pop("node_type"))),
    "geometries not JSON": ("zarr.json", lambda p: _edit_json(
        p, lambda d: d["attributes"].update(sonarmap_geometries="[{"))),
    "sources a number": ("zarr.json", lambda p: _edit_json(p, lambda d: d["attributes"].update(sonarmap_sources=5))),
    "data model missing": ("zarr.json", lambda p: _edit_json(p, lambda d: d["attributes"].pop("sonarmap_data_model"))),
    "intensity truncated": ("intensity/zarr.json", lambda p: p.write_bytes(p.read_bytes()[:40])),
    "intensity shape a string": ("intensity/zarr.json", lambda p: _edit_json(p, lambda d: d.update(shape="x"))),
    "intensity without data_type": ("intensity/zarr.json", lambda p: _edit_json(p, lambda d: d.pop("data_type"))),
    "intensity codecs a dict": ("intensity/zarr.json", lambda p: _edit_json(p, lambda d: d.update(codecs={}))),
    "intensity chunk grid bogus": ("intensity/zarr.json", lambda p: _edit_json(
        p, lambda d: d.update(chunk_grid={"name": "regular", "configuration": {"chunk_shape": "x"}}))),
    "geometry_index invalid UTF-8": ("geometry_index/zarr.json", lambda p: p.write_bytes(b"\x80" + p.read_bytes())),
    "geometry_index dims wrong": ("geometry_index/zarr.json", lambda p: _edit_json(
        p, lambda d: d.update(dimension_names=[1]))),
    "ping_time units days": ("ping_time/zarr.json", lambda p: _edit_json(
        p, lambda d: d["attributes"].update(units="days since 1970-01-01"))),
    "ping_time data type float": ("ping_time/zarr.json", lambda p: _edit_json(p, lambda d: d.update(data_type="float64"))),
    "meta kind bogus": ("meta_frame/zarr.json", lambda p: _edit_json(
        p, lambda d: d["attributes"].update(sonarmap_kind=["int"]))),
}


@pytest.mark.parametrize("case", sorted(BAD_JSON))
@pytest.mark.slow
def test_bad_zarr_json_is_one_clean_error(case: str, seeds: dict[str, Path], tmp_path: Path) -> None:
    rel, mutate = BAD_JSON[case]
    store = _copy(seeds["raw"], tmp_path)
    mutate(store / rel)
    for read in (_read_all, zarrstore.summary, zarrstore.count_pings):
        with pytest.raises(SonarmapError) as ei:
            read(store)
        msg = _one_line_error(store, ei.value)
        assert ("zarr.json" in msg) or (rel.split("/")[0] in msg), msg


@pytest.mark.parametrize("array", ["geometry_index", "ping_time", "source_index", "intensity"])
def test_deleted_required_array(array: str, seeds: dict[str, Path], tmp_path: Path) -> None:
    store = _copy(seeds["raw"], tmp_path)
    shutil.rmtree(store / array)
    with pytest.raises(DataFormatError, match=array) as ei:
        _read_all(store)
    _one_line_error(store, ei.value)
    with pytest.raises(DataFormatError, match=array):
        zarrstore.summary(store)  # was: a 1970 time span for a deleted ping_time


@pytest.mark.parametrize("case", ["kld zarr.json truncated", "ping_time deleted", "flags deleted",
                                  "range chunk truncated", "root invalid UTF-8", "kld shape", "schema a string",
                                  "confidence out of range", "ping_time chunk deleted"])
def test_report_on_corrupt_store_prints_one_line(case: str, seeds: dict[str, Path], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main

    store = _copy(seeds["prod"], tmp_path)
    if case == "kld zarr.json truncated":
        p = store / "kld" / "zarr.json"
        p.write_bytes(p.read_bytes()[:40])
    elif case == "ping_time deleted":
        shutil.rmtree(store / "ping_time")
    elif case == "flags deleted":
        shutil.rmtree(store / "flags")
    elif case == "range chunk truncated":
        p = store / "range" / "c" / "0" / "0"
        p.write_bytes(p.read_bytes()[:10])
    elif case == "root invalid UTF-8":
        p = store / "zarr.json"
        p.write_bytes(b"\xff" + p.read_bytes())
    elif case == "kld shape":
        _edit_json(store / "kld" / "zarr.json", lambda d: d.update(shape=[3]))
    elif case == "schema a string":
        _edit_json(store / "zarr.json", lambda d: d["attributes"].update(schema="x"))
    elif case == "confidence out of range":
        import zarr

        zarr.open_group(str(store), mode="r+")["range_confidence"][1, 2] = 5.0
    elif case == "ping_time chunk deleted":
        (store / "ping_time" / "c" / "1").unlink()
    capsys.readouterr()
    rc = main(["report", str(store), "-o", str(tmp_path / "r.html"), "--examples", "0"])
    gc.collect()  # zarr's event loop logs unretrieved task errors when they are collected
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert rc == 1, err
    assert len(lines) == 1 and lines[0].startswith("sonarmap: error: "), err
    assert "Traceback" not in err and str(store) in err
    assert not (tmp_path / "r.html").exists()
    if case == "confidence out of range":
        assert "range_confidence: ping 1 at index (2,): value 5.0 is outside the documented range [0, 1]" in err


@pytest.mark.slow
def test_report_of_a_sound_store_still_works(seeds: dict[str, Path], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main
    from sonarmap.survey import load_products

    ds = load_products(seeds["prod"])
    assert ds.sizes["ping_time"] == 4 and np.isfinite(ds["range"].values).any()
    rc = main(["report", str(seeds["prod"]), "-o", str(tmp_path / "r.html"), "--examples", "0"])
    assert rc == 0, capsys.readouterr().err
    assert "2020-09-13" in (tmp_path / "r.html").read_text(encoding="utf-8")  # the real span, not 1970


@pytest.mark.slow  # over a second in the fast subset
def test_product_store_with_labels_and_points_loads_and_is_checked(seeds: dict[str, Path], tmp_path: Path) -> None:
    import zarr

    from sonarmap.mapping import Trajectory, write_trajectory_csv
    from sonarmap.survey import load_products, process_survey

    tt = np.array([T0 - 10**9, T0 + 10**9])
    traj = Trajectory(tt, np.array([[0.0, 0, 0], [2.0, 0, 0]]), np.array([[0, 0, 0, 1.0]] * 2))
    write_trajectory_csv(traj, tmp_path / "poses.csv")
    out = tmp_path / "lp.zarr"
    res = process_survey([seeds["raw"]], out, workers=0, chunk_size=2, keep_labels=True,
                         poses=tmp_path / "poses.csv", ping_function=fake_ping_function)
    ds = load_products(out)
    assert res.n_points == ds.sizes["point"] == int(np.isfinite(ds["range"].values).sum()) > 0
    assert ds["labels"].shape == (4, 8, 4) and "crc32c" in (out / "point_xyz" / "zarr.json").read_text()
    zarr.open_group(str(out), mode="r+")["point_beam"][1] = 99
    with pytest.raises(DataFormatError, match=r"point_beam: point 1: value 99 is outside the documented range \[0, 3\]"):
        load_products(out)


# ---------------------------------------------------------------------------- values on read
@pytest.mark.parametrize("value", [-9e35, 1e30, 5.0, -0.001, np.nan, np.inf])
def test_bad_float_pixels_are_errors_naming_store_variable_and_ping(
    value: float, seeds: dict[str, Path], tmp_path: Path,
) -> None:
    import zarr

    store = _copy(seeds["raw"], tmp_path)
    zarr.open_group(str(store), mode="r+")["intensity"][3, 5, 1] = value  # a valid chunk (checksum ok)
    with pytest.raises(DataFormatError) as ei:
        _read_all(store)
    msg = _one_line_error(store, ei.value)
    assert "intensity: ping 3 at index (5, 1): value" in msg


def test_writer_refuses_pixels_and_times_a_store_cannot_hold(tmp_path: Path) -> None:
    p = _pings(1)[0]
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        write_survey([p.replace(image=p.image * 5)], tmp_path / "a.zarr")
    with pytest.raises(InputError, match="time"):  # was: OverflowError from numpy
        write_survey([p.replace(time_ns=2**63)], tmp_path / "b.zarr")
    with pytest.raises(InputError, match="ping time -1 ns is outside"):
        write_survey([p.replace(time_ns=-1)], tmp_path / "c.zarr")
    assert not list(tmp_path.iterdir())  # nothing left behind, no lock file either


@pytest.mark.parametrize("case", ["negative", "NaT", "uint64 beyond int64"])
def test_times_are_checked_on_read(case: str, seeds: dict[str, Path], tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    import zarr

    from sonarmap.cli import main

    store = _copy(seeds["raw"], tmp_path)
    g = zarr.open_group(str(store), mode="r+")
    if case == "uint64 beyond int64":
        attrs = dict(g["ping_time"].attrs)
        times = g["ping_time"][:].astype(np.uint64)
        times[2] = np.uint64(2**63 + 5)
        del g["ping_time"]
        a = g.create_array("ping_time", shape=times.shape, dtype=np.uint64, dimension_names=("ping_time",),
                           attributes=attrs)
        a[...] = times
        want = "data type uint64"
    else:
        g["ping_time"][2] = -5 if case == "negative" else np.iinfo(np.int64).min
        want = "ping_time: ping 2: time is " + ("-5 ns, before 1970" if case == "negative" else "not a time (NaT)")
    for read in (_read_all, zarrstore.summary):
        with pytest.raises(DataFormatError, match=re.escape(want)) as ei:
            read(store)
        _one_line_error(store, ei.value)
    capsys.readouterr()
    assert main(["info", str(store)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and want in err, err


@pytest.mark.timeout(120)
@pytest.mark.parametrize("case", ["FIFO chunk", "/dev/zero chunk", "FIFO zarr.json", "huge shape", "huge chunks"])
def test_special_files_and_absurd_sizes_never_hang(case: str, seeds: dict[str, Path], tmp_path: Path) -> None:
    """A chunk file or metadata document replaced by a FIFO (zarr would block on it forever) or a
    link to /dev/zero (read without end), and absurd shapes or chunk sizes in the metadata: one
    clean error, at once."""
    store = _copy(seeds["raw"], tmp_path)
    if case == "FIFO chunk":
        (store / "source_index" / "c" / "1").unlink()
        os.mkfifo(store / "source_index" / "c" / "1")
    elif case == "/dev/zero chunk":
        (store / "ping_time" / "c" / "0").unlink()
        (store / "ping_time" / "c" / "0").symlink_to("/dev/zero")
    elif case == "FIFO zarr.json":
        (store / "echo_range" / "zarr.json").unlink()
        os.mkfifo(store / "echo_range" / "zarr.json")
    elif case == "huge shape":
        _edit_json(store / "range_sample" / "zarr.json", lambda d: d.update(shape=[10**9]))
    else:
        _edit_json(store / "intensity" / "zarr.json",
                   lambda d: d["chunk_grid"]["configuration"].update(chunk_shape=[10**6, 8, 10**6]))
    t = time.monotonic()
    with pytest.raises(DataFormatError) as ei:
        _read_all(store)
    _one_line_error(store, ei.value)
    assert time.monotonic() - t < 30


def test_an_unfinished_product_store_still_loads(seeds: dict[str, Path], tmp_path: Path) -> None:
    """Chunks of tasks not yet done are missing by design (fill values), not damage."""
    from sonarmap.survey import load_products

    store = _copy(seeds["prod"], tmp_path)
    for f in (store / ".sonarmap" / "chunks").glob("00000001.done"):
        f.unlink()
    (store / ".sonarmap" / "complete").unlink()
    for name in ("ping_time", "range", "kld", "flags", "source"):
        c1 = store / name / "c" / "1"
        shutil.rmtree(c1) if c1.is_dir() else c1.unlink()  # chunk 1 of 1-D (a file) or 2-D arrays
    ds = load_products(store)
    assert ds["ping_time"].values.astype(np.int64)[2:].tolist() == [0, 0]
    assert np.isnan(ds["range"].values[2:]).all()
    (store / ".sonarmap" / "chunks" / "00000001.done").write_text("{}")  # claims done: now it is damage
    with pytest.raises(DataFormatError, match="chunk c/1: missing"):
        load_products(store)


# ---------------------------------------------------------------------------- checksums
@pytest.mark.slow
def test_chunks_are_checksummed_and_old_stores_still_read(seeds: dict[str, Path], tmp_path: Path) -> None:
    """Every array of both writers has a crc32c codec; a store written without (before this
    change) reads as before - raw and product stores, the product one also resumes."""
    import sonarmap.store.products as ss
    from sonarmap.store import pings_to_dataset
    from sonarmap.store.writer import _encoding
    from sonarmap.survey import load_products, process_survey

    for store in (seeds["raw"], seeds["prod"]):
        for meta in store.glob("*/zarr.json"):
            names = [c["name"] for c in json.loads(meta.read_text())["codecs"]]
            assert names[-2:] == ["zstd", "crc32c"], (meta, names)
    # An old raw store: the encoding of the previous writer (zarr's default codecs, bytes + zstd).
    old = tmp_path / "old.zarr"
    ds = pings_to_dataset(_pings())
    enc = _encoding(ds, 2)
    for e in enc.values():
        e.pop("compressors", None)
    ds.to_zarr(old, mode="w", encoding=enc, consolidated=False)
    assert "crc32c" not in (old / "intensity" / "zarr.json").read_text()
    assert _same_pings(_read_all(old), _read_all(seeds["raw"]))
    assert [p.time_ns for p in _read_all(old)] == [p.time_ns for p in _pings()]
    # ... and a zarr v2 store (.zgroup/.zarray/.zattrs) of the same pings.
    v2 = tmp_path / "v2.zarr"
    for e in enc.values():
        e.pop("fill_value", None)
    ds.to_zarr(v2, mode="w", encoding=enc, consolidated=False, zarr_format=2)
    assert (v2 / ".zgroup").exists() and _same_pings(_read_all(v2), _read_all(seeds["raw"]))
    assert zarrstore.summary(v2)["zarr_format"] == 2
    # An old product store: no crc32c codec (chunks are written in the layout the store has).
    from zarr.codecs import ZstdCodec

    def old_kwargs() -> dict[str, Any]:
        return {"compressors": ZstdCodec(level=0, checksum=False),
                "chunk_key_encoding": {"name": "default", "separator": "/"}}

    orig = ss.array_codec_kwargs
    ss.array_codec_kwargs = old_kwargs
    try:
        oldp = tmp_path / "oldp.zarr"
        process_survey([seeds["raw"]], oldp, workers=0, chunk_size=2, ping_function=fake_ping_function)
    finally:
        ss.array_codec_kwargs = orig
    assert "crc32c" not in (oldp / "range" / "zarr.json").read_text()
    for m in (oldp / ".sonarmap" / "chunks").iterdir():
        m.unlink()  # as if interrupted: the resumed run rewrites the chunks (without checksums)
    (oldp / ".sonarmap" / "complete").unlink()
    res = process_survey([seeds["raw"]], oldp, workers=0, chunk_size=2, ping_function=fake_ping_function)
    assert res.chunks_run == 2
    a, b = load_products(oldp), load_products(seeds["prod"])
    for name in ("range", "kld", "ping_time", "flags", "range_bin", "mixture_param"):
        assert a[name].values.tolist() == b[name].values.tolist() or np.array_equal(
            a[name].values, b[name].values, equal_nan=True), name


@pytest.mark.slow
def test_200_single_bit_flips_never_change_data_silently(seeds: dict[str, Path], tmp_path: Path) -> None:
    """Seeded: 170 flips in the chunk files of a raw store (read as pings) and 30 in a product
    store (read by load_products, what the report reads).  With checksums each flip is an
    error naming the array and chunk; none may decode to changed values."""
    from sonarmap.survey import load_products

    rng = np.random.default_rng(20240601)
    raw = _copy(seeds["one"], tmp_path)  # one chunk per array: each read is one block
    prod = _copy(seeds["prod"], tmp_path)
    want = _read_all(raw)
    ds = open_survey(raw)  # flips in chunks of non-index arrays are read through the same dataset
    index = {"ping_time", "range_sample", "beam"}
    silent = raised = 0
    for store, n_flips in ((raw, 170), (prod, 30)):
        files = _chunk_files(store)
        for _ in range(n_flips):
            f = files[int(rng.integers(len(files)))]
            data = bytearray(f.read_bytes())
            pos, bit = int(rng.integers(len(data))), int(rng.integers(8))
            data[pos] ^= 1 << bit
            f.write_bytes(bytes(data))
            array = f.relative_to(store).parts[0]
            try:
                if store is prod:
                    load_products(prod)
                elif array in index:
                    _read_all(raw)
                else:
                    got = list(dataset_to_pings(ds))
                    silent += not _same_pings(got, want)
            except SonarmapError as exc:
                raised += 1
                assert f"array '{array}', chunk " in str(exc) and "\n" not in str(exc), str(exc)
            finally:
                data[pos] ^= 1 << bit
                f.write_bytes(bytes(data))
    assert silent == 0
    assert raised == 200  # every flip is detected (CRC32C catches every single-bit error)
    assert _same_pings(_read_all(raw), want)


# ---------------------------------------------------------------------------- mini-fuzz
def _mutation(rng: np.random.Generator, store: Path) -> tuple[str, Path, bytes | None]:
    """One random mutation of one metadata document or chunk file of ``store``: what it was, the
    file, and its new content (``None``: deleted)."""
    metas = sorted(store.glob("**/zarr.json"))
    chunks = _chunk_files(store)
    kind = ["truncate json", "invalid utf-8", "wrong type", "delete key", "wrong type", "delete key",
            "delete chunk", "truncate chunk"][int(rng.integers(8))]
    if kind in ("delete chunk", "truncate chunk"):
        f = chunks[int(rng.integers(len(chunks)))]
        if kind == "delete chunk":
            return f"{kind} {f.relative_to(store)}", f, None
        n = int(rng.integers(0, f.stat().st_size))
        return f"{kind} {f.relative_to(store)} to {n}", f, f.read_bytes()[:n]
    m = metas[int(rng.integers(len(metas)))]
    raw = m.read_bytes()
    if kind == "truncate json":
        n = int(rng.integers(0, len(raw)))
        return f"{kind} {m.relative_to(store)} to {n}", m, raw[:n]
    if kind == "invalid utf-8":
        i = int(rng.integers(0, len(raw)))
        return f"{kind} {m.relative_to(store)} at {i}", m, raw[:i] + b"\xc3\x28" + raw[i:]
    doc = json.loads(raw)
    slots: list[tuple[Any, Any]] = []  # every (container, key) of the document, nested

    def walk(x: Any) -> None:
        items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list) else ()
        for k, v in items:
            slots.append((x, k))
            walk(v)

    walk(doc)
    if kind == "delete key":
        slots = [(c, k) for c, k in slots if isinstance(c, dict)]
    c, k = slots[int(rng.integers(len(slots)))]
    if kind == "delete key":
        del c[k]
    else:
        others = [None, True, -3, 2.5, "x", [], {}, [1, "a"], {"a": 1}]
        choices = [o for o in others if type(o) is not type(c[k])]
        c[k] = choices[int(rng.integers(len(choices)))]
    return f"{kind} {m.relative_to(store)} [{k!r}]", m, json.dumps(doc).encode()


@pytest.mark.slow
def test_seeded_mini_fuzz_gives_clean_errors_or_the_same_data(seeds: dict[str, Path], tmp_path: Path) -> None:
    """200 seeded mutations (truncated / non-UTF-8 metadata, wrong types, deleted keys, deleted or
    truncated chunks) of a raw store (read as pings) and a product store (load_products): each
    case is a SonarmapError or reads the original data exactly."""
    from sonarmap.survey import load_products

    rng = np.random.default_rng(4242)
    stores = {"one": _copy(seeds["one"], tmp_path), "prod": _copy(seeds["prod"], tmp_path)}
    want = _read_all(stores["one"])
    want_p = load_products(stores["prod"])
    outcomes = {"error": 0, "same": 0}
    for i in range(200):
        store = stores["one"] if i % 8 else stores["prod"]
        what, f, content = _mutation(rng, store)
        before = f.read_bytes()
        if content is None:
            f.unlink()
        else:
            f.write_bytes(content)
        try:
            if store is stores["prod"]:
                got = load_products(store)
                for name in want_p.variables:
                    x, y = want_p[name].values, got[name].values
                    same = x.tolist() == y.tolist() if x.dtype.kind not in "f" else np.array_equal(
                        x, y, equal_nan=True)
                    assert same and x.dtype == y.dtype, f"case {i} ({what}): {name} changed silently"
            else:
                assert _same_pings(_read_all(store), want), f"case {i} ({what}): pings changed silently"
            outcomes["same"] += 1
        except SonarmapError as exc:
            assert "\n" not in str(exc) and str(store) in str(exc), f"case {i} ({what}): {exc}"
            outcomes["error"] += 1
        except Exception as exc:  # noqa: BLE001 - the defect this test is for
            pytest.fail(f"case {i} ({what}): foreign {type(exc).__name__}: {exc}")
        finally:
            f.write_bytes(before)  # the same store serves the next case
    print(f"mini-fuzz outcomes: {outcomes}")
    assert sum(outcomes.values()) == 200 and outcomes["error"] > 100, outcomes
    assert _same_pings(_read_all(stores["one"]), want)


# ---------------------------------------------------------------------------- writers
_HOLD = """
import sys, time
from sonarmap._atomic import WriterLock
lock = WriterLock(sys.argv[1]).acquire()
print("held", flush=True)
time.sleep(60)
"""


@pytest.mark.slow
def test_two_writers_on_one_store(seeds: dict[str, Path], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main
    from sonarmap.survey import process_survey

    store = tmp_path / "s.zarr"
    with SurveyWriter(store, chunk_pings=2) as w:
        w.add(_pings(1)[0])
        for second in (lambda: SurveyWriter(store, mode="a"), lambda: write_survey(_pings(), store),
                       lambda: process_survey([seeds["raw"]], store, workers=0, chunk_size=2,
                                              ping_function=fake_ping_function)):
            with pytest.raises(DataFormatError, match=rf"s\.zarr: in use by another writer \(pid {os.getpid()}\)"):
                second()
    assert len(_read_all(store)) == 1 and not (tmp_path / ".s.zarr.lock").exists()
    # Another process holds the store: `sonarmap convert` says so in one line and writes nothing.
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(store)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        capsys.readouterr()
        assert main(["convert", str(seeds["raw"]), "-o", str(store), "--append", "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert err.splitlines() == [f"sonarmap: error: {store}: in use by another writer (pid {holder.pid}); "
                                    "wait for it to finish or stop it"], err
        assert len(_read_all(store)) == 1
    finally:
        holder.kill()
        holder.wait()
    # The killed holder's lock file is left behind; the next writer takes it over.
    assert json.loads((tmp_path / ".s.zarr.lock").read_text())["pid"] == holder.pid
    write_survey(_pings(), store, append=True)
    assert len(_read_all(store)) == 5 and not (tmp_path / ".s.zarr.lock").exists()


@pytest.mark.slow  # starts a child process
def test_interrupted_process_resumes_over_a_stale_lock(seeds: dict[str, Path], tmp_path: Path) -> None:
    from sonarmap.survey import load_products, process_survey, survey_status

    out = tmp_path / "p.zarr"
    calls: list[int] = []

    def stop(done: int, total: int) -> None:
        calls.append(done)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        process_survey([seeds["raw"]], out, workers=0, chunk_size=2, ping_function=fake_ping_function,
                       progress=stop)
    assert survey_status(out)["done"] == 1 and not (tmp_path / ".p.zarr.lock").exists()
    dead = _dead_pid()
    (tmp_path / ".p.zarr.lock").write_text(json.dumps({"pid": dead, "host": os.uname().nodename}))
    (tmp_path / ".p.zarr.abcd1234.tmp").mkdir()  # a new store a killed run was building
    marker_tmp = out / ".sonarmap" / "chunks" / f".00000001.done.{dead}-abcdef.k2j3h4g5.tmp.done"
    marker_tmp.write_text("{")  # a marker a killed run was writing
    res = process_survey([seeds["raw"]], out, workers=0, chunk_size=2, ping_function=fake_ping_function)
    assert res.chunks_skipped == 1 and res.chunks_run == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.zarr"] and not marker_tmp.exists()
    a, b = load_products(out), load_products(seeds["prod"])
    assert np.array_equal(a["range"].values, b["range"].values, equal_nan=True)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.mark.slow  # starts a child process
def test_stale_temporaries_of_killed_runs_are_removed(tmp_path: Path, test_ping_paths: list[Path],
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """What a killed ``sonarmap ranges`` leaves (``.ranges.csv.<pid>-<host>.<random>.tmp.csv``) is
    removed by the next run writing the same file; live runs' and other files' temporaries stay."""
    from sonarmap._atomic import _host_tag
    from sonarmap.cli import main

    target = tmp_path / "ranges.csv"
    host, dead = _host_tag(), _dead_pid()
    stale = [tmp_path / f".ranges.csv.{dead}-{host}.k2j3h4g5.tmp.csv", tmp_path / ".ranges.csv.q1w2e3r4.tmp.csv"]
    keep = [tmp_path / f".ranges.csv.{os.getppid()}-{host}.a1b2c3d4.tmp.csv",  # a live process
            tmp_path / f".ranges.csv.{dead}-ffffff.a1b2c3d4.tmp.csv",  # another host, recent
            tmp_path / ".ranges.csv.z9y8x7w6.tmp.csv",  # no pid, recent
            tmp_path / f".other.csv.{dead}-{host}.k2j3h4g5.tmp.csv"]  # another target
    for p in stale + keep:
        p.write_text("partial")
    old = time.time() - 2 * 3600
    os.utime(stale[1], (old, old))
    assert main(["ranges", str(test_ping_paths[0]), "-o", str(target)]) == 0
    assert target.read_text(encoding="utf-8").startswith("ping,beam,")
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in keep)
    # A store writer removes what killed writers of the same store left beside it.
    (tmp_path / ".s.zarr.abcd1234.tmp" / "store.zarr").mkdir(parents=True)
    (tmp_path / ".s.zarr.old-12345").mkdir()
    write_survey(_pings(1), tmp_path / "s.zarr")
    assert not list(tmp_path.glob(".s.zarr*"))


def test_disk_full_names_the_target(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import xarray as xr

    from sonarmap._atomic import atomic_write_text

    target = tmp_path / "out.csv"
    target.write_text("before")

    def full(*_: Any, **__: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(os, "fsync", full)
        with pytest.raises(DataFormatError, match=rf"{target}: cannot write: No space left on device"):
            atomic_write_text(target, "after")
    assert target.read_text() == "before" and sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]
    def full_store(*_: Any, **__: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / ".tmpdir" / "c" / "0"))

    with monkeypatch.context() as m:
        m.setattr(xr.Dataset, "to_zarr", full_store)
        store = tmp_path / "s.zarr"
        with pytest.raises(DataFormatError, match=rf"{store}: cannot write the store: No space left on device"):
            write_survey(_pings(1), store)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]  # no store, temporaries or lock
