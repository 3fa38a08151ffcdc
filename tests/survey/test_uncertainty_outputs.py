"""Range sigma, per-beam pD and further surfaces in the ranges CSV and the survey store."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sonarmap.ranges import BeamRanges


def _ranges(n: int = 5) -> BeamRanges:
    return BeamRanges(
        range_m=np.array([4.0, np.nan, 5.123456789, 6.5, np.nan][:n]),
        bin=np.array([100, -1, 163, 242, -1][:n]),
        intensity=np.array([0.5, np.nan, 0.25, 0.75, np.nan][:n], np.float32),
        confidence=np.ones(n, np.float32),
        azimuth_rad=np.linspace(-0.2, 0.2, n),
        sigma_m=np.array([0.0125, np.nan, np.nan, 0.031, np.nan][:n]),
        p_detect=np.array([0.9, 0.5, np.nan, 0.75, np.nan][:n], np.float32),
    )


def test_csv_rows_carry_sigma_and_p_detect() -> None:
    from sonarmap.ranges.csv_rows import CSV_HEADER, write_ranges_rows

    assert CSV_HEADER[:9] == ("ping", "beam", "azimuth_rad", "bin", "range_m", "intensity", "flags", "sigma_m",
                              "p_detect")
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(CSV_HEADER)
    assert write_ranges_rows(w, "p.png", _ranges(), "kld") == 5
    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert [r["sigma_m"] for r in rows] == ["0.0125", "", "", "0.031", ""]  # empty: no return or no estimate
    assert [r["p_detect"] for r in rows] == ["0.9", "0.5", "", "0.75", ""]  # a beam property: set without a return
    assert [r["range_m"] for r in rows] == ["4.000000", "", "5.123457", "6.500000", ""]
    assert [r["bin"] for r in rows] == ["100", "", "163", "242", ""]
    assert all(r["flags"] == "kld" for r in rows)
    # defaults (nothing estimated yet): both columns empty on every row
    buf = io.StringIO()
    br = dataclasses.replace(_ranges(), sigma_m=None, p_detect=None)
    write_ranges_rows(csv.writer(buf), "p.png", br)
    assert all(r[7:9] == ["", ""] for r in csv.reader(io.StringIO(buf.getvalue())))


def test_ranges_command_writes_the_new_columns(tmp_path: Path, test_ping_paths: list[Path],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import sonarmap.pipeline as pipeline
    from sonarmap.cli import main

    real = pipeline.process_ping

    def with_uncertainty(ping, config, **kw):  # noqa: ANN001, ANN202
        prod = real(ping, config, **kw)
        r = prod.ranges
        sig = np.where(r.valid, 0.01 + 0.001 * np.arange(r.n_beams), np.nan)
        return dataclasses.replace(prod, ranges=dataclasses.replace(
            r, sigma_m=sig, p_detect=np.full(r.n_beams, 0.875, np.float32)))

    monkeypatch.setattr(pipeline, "process_ping", with_uncertainty)
    out = tmp_path / "r.csv"
    assert main(["ranges", str(test_ping_paths[4]), "-o", str(out)]) == 0
    rows = list(csv.DictReader(out.open(newline="")))
    assert list(rows[0])[:9] == ["ping", "beam", "azimuth_rad", "bin", "range_m", "intensity", "flags",
                                 "sigma_m", "p_detect"]
    assert len(rows) == 96 and sum(1 for r in rows if r["bin"]) > 40  # a hull ping
    for r in rows:
        assert r["p_detect"] == "0.875"
        if r["bin"]:
            assert float(r["sigma_m"]) == pytest.approx(0.01 + 0.001 * int(r["beam"]))
        else:
            assert r["sigma_m"] == ""


# ---------------------------------------------------------------------- survey store
def with_uncertainty(ping, config, *, keep_labels=False):  # noqa: ANN001, ANN201
    """The pipeline, with known sigma / p_detect / further surfaces (3 behind each return)."""
    from sonarmap.pipeline import process_ping

    prod = process_ping(ping, config, keep_labels=keep_labels)
    r = prod.ranges
    j = np.arange(r.n_beams)
    others = np.where(r.valid, 10.0 + 0.01 * j, np.nan) + np.array([[0.5], [1.0], [1.5]])
    return dataclasses.replace(prod, ranges=dataclasses.replace(
        r, sigma_m=np.where(r.valid, 0.002 * (1 + j % 7), np.nan),
        p_detect=(0.5 + 0.004 * j).astype(np.float32), other_range_m=others))


def _expected(name: str, r: np.ndarray, n_beams: int) -> np.ndarray:
    j = np.arange(n_beams)
    valid = np.isfinite(r)
    return {
        "range_sigma": np.where(valid, 0.002 * (1 + j % 7), np.nan).astype(np.float32),
        "p_detect": np.broadcast_to((0.5 + 0.004 * j).astype(np.float32), r.shape),
        "other_range": (np.where(valid, 10.0 + 0.01 * j, np.nan)[:, None, :]
                        + np.array([[0.5], [1.0]])).astype(np.float32),
    }[name]


def _pings(tmp_path: Path, test_ping_paths: list[Path], n: int = 4) -> Path:
    from sonarmap.survey import replicate_pings

    return replicate_pings([test_ping_paths[i] for i in (4, 1, 6, 8)][:n], n, tmp_path / "pings")


def test_store_round_trips_sigma_p_detect_and_further_surfaces(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    from sonarmap.survey import N_OTHER_RETURNS, open_products, process_survey

    src = _pings(tmp_path, test_ping_paths)
    out = tmp_path / "s.zarr"
    process_survey([src], out, workers=0, chunk_size=3, ping_function=with_uncertainty)
    ds = open_products(out).load()
    r = ds["range"].values
    assert np.isfinite(r).sum() > 100
    for name, dims, units in (("range_sigma", ("ping_time", "beam"), "m"), ("p_detect", ("ping_time", "beam"), "1"),
                              ("other_range", ("ping_time", "other_return", "beam"), "m")):
        v = ds[name]
        assert v.dims == dims and v.dtype == np.float32, name
        assert v.attrs["units"] == units and v.attrs["long_name"] and v.attrs["description"], name
        np.testing.assert_array_equal(v.values, _expected(name, r, r.shape[1]), err_msg=name)
    assert ds.sizes["other_return"] == N_OTHER_RETURNS  # the third surface is not stored
    assert "beam_azimuth" in ds["range_sigma"].coords
    # the pipeline's own products: stored as process_ping reports them (float32, NaN-padded)
    from sonarmap.io import read_pings
    from sonarmap.pipeline import PipelineConfig, process_ping

    plain = tmp_path / "plain.zarr"
    process_survey([src], plain, workers=0, chunk_size=3)
    dp = open_products(plain).load()
    for i, ping in enumerate(read_pings(str(src))):
        br = process_ping(ping, PipelineConfig()).ranges
        np.testing.assert_array_equal(dp["range_sigma"].values[i], br.sigma_m.astype(np.float32))
        np.testing.assert_array_equal(dp["p_detect"].values[i], br.p_detect)
        other = np.full((N_OTHER_RETURNS, br.n_beams), np.nan, np.float32)
        k = min(N_OTHER_RETURNS, br.other_range_m.shape[0])
        other[:k] = br.other_range_m[:k]
        np.testing.assert_array_equal(dp["other_range"].values[i], other)


def test_store_points_carry_sigma(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    from sonarmap.mapping import read_point_cloud
    from sonarmap.survey import open_products, process_survey

    src = _pings(tmp_path, test_ping_paths, n=2)
    times = [1_500_000_000_000_000_000 + k * 100_000_000 for k in (-10, 30)]
    poses = tmp_path / "poses.csv"
    poses.write_text("time_ns,x,y,z,qx,qy,qz,qw\n" + "".join(f"{t},0,0,0,0,0,0,1\n" for t in times), encoding="utf-8")
    out = tmp_path / "s.zarr"
    res = process_survey([src], out, workers=0, chunk_size=2, poses=poses, ping_function=with_uncertainty)
    ds = open_products(out).load()
    sig = ds["range_sigma"].values
    want = sig[np.isfinite(ds["range"].values)]
    assert res.n_points == want.size > 40
    np.testing.assert_array_equal(ds["point_range_sigma"].values, want)
    assert ds["point_range_sigma"].attrs["units"] == "m"
    np.testing.assert_array_equal(read_point_cloud(res.points_path).sigma_m, want)


def test_store_without_the_new_variables_resumes_and_reads(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    """A store created before range_sigma / p_detect / other_range existed: a resumed run writes
    the variables the store was created with (its schema), and the store reads as before."""
    import zarr

    from sonarmap.survey import open_products, process_survey

    src = _pings(tmp_path, test_ping_paths)
    out = tmp_path / "old.zarr"
    process_survey([src], out, workers=0, chunk_size=2)
    new = ("range_sigma", "p_detect", "other_range")
    root = zarr.open_group(str(out), mode="r+", zarr_format=3)
    schema = dict(root.attrs["schema"])
    for name in new:
        del root[name]
        del schema[name]
    root.attrs["schema"] = schema
    for name in new:
        assert not (out / name).exists()
    ref = open_products(out).load()
    # interrupt: chunk 1 lost its data and marker, the run never completed
    (out / ".sonarmap" / "complete").unlink()
    (out / ".sonarmap" / "chunks" / "00000001.done").unlink()
    shutil.rmtree(out / "range" / "c" / "1")
    res = process_survey([src], out, workers=0, chunk_size=2)
    assert res.chunks_run == 1 and res.chunks_skipped == 1
    ds = open_products(out).load()
    assert not set(new) & set(ds.variables)
    assert sorted(ds.variables) == sorted(ref.variables)
    for name in ds.variables:
        a, b = ds[name].values, ref[name].values
        if a.dtype.kind == "f":
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a.tolist() == b.tolist(), name
    assert json.loads((out / ".sonarmap" / "complete").read_text())["n_pings"] == 4
