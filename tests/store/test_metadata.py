"""One data model for both zarr stores: the raw-ping store of ``sonarmap convert`` and the product
store of ``sonarmap process`` share one coordinate layout (:mod:`sonarmap.datamodel`), carry
consolidated metadata kept in step with their arrays (:mod:`sonarmap.store.metadata`; so
``xarray.open_zarr`` opens them without a warning), and ``sonarmap info`` / ``sonarmap show`` accept a product store."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from sonarmap.cli import main
from sonarmap.datamodel import (
    COORD_AZIMUTH,
    COORD_RANGE,
    COORDINATES,
    DIM_BEAM,
    DIM_PING,
    DIM_RANGE,
)
from sonarmap.errors import DataFormatError
from sonarmap.store import consolidated_status

N = 4


def _cli(args: list[str]) -> None:
    """Run ``sonarmap ARGS`` in this process; it must succeed (exit code 0)."""
    try:
        rc = main(args)
    except SystemExit as exc:
        rc = exc.code
    assert rc in (0, None), f"sonarmap {' '.join(args)} exited {rc}"


@pytest.fixture(scope="module")
def paths(test_ping_paths: list[Path]) -> list[str]:
    return [str(p) for p in test_ping_paths[:N]]


@pytest.fixture(scope="module")
def stores(paths: list[str], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("schema")
    out = {"converted": d / "c.zarr", "processed": d / "p.zarr", "labels": d / "l.zarr"}
    _cli(["convert", *paths, "-o", str(out["converted"]), "-q"])
    _cli(["process", *paths, "-o", str(out["processed"]), "--workers", "0", "-q", "--chunk-size", "2"])
    _cli(["process", *paths, "-o", str(out["labels"]), "--workers", "0", "-q", "--keep-labels"])
    return out


def _open_strict(store: Path) -> subprocess.CompletedProcess[str]:
    code = f"import xarray as xr; ds = xr.open_zarr({str(store)!r}); print(ds.sizes['{DIM_PING}'])"
    return subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("kind", ["converted", "processed", "labels"])
@pytest.mark.slow
def test_xarray_opens_both_store_kinds_without_a_warning(stores: dict[str, Path], kind: str) -> None:
    r = _open_strict(stores[kind])
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(r.stdout.strip()) == N
    assert consolidated_status(stores[kind]) == "current"


def test_both_store_kinds_have_the_same_coordinate_layout(stores: dict[str, Path],
                                                          test_pings: list) -> None:  # noqa: ANN001
    import xarray as xr

    a = xr.open_zarr(stores["converted"])
    b = xr.open_zarr(stores["processed"])
    for name, dims in COORDINATES.items():
        assert name in a.coords and name in b.coords, name
        assert a[name].dims == b[name].dims == dims, name
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
    g = test_pings[0].geometry
    np.testing.assert_array_equal(b[COORD_RANGE].values, np.broadcast_to(g.range_m, (N, g.n_bins)))
    np.testing.assert_array_equal(b[COORD_AZIMUTH].values, g.azimuth_rad)
    assert a[COORD_RANGE].attrs == b[COORD_RANGE].attrs and a[COORD_AZIMUTH].attrs["units"] == "rad"
    assert b["range"].dims == (DIM_PING, DIM_BEAM) and COORD_AZIMUTH in b["range"].coords


@pytest.mark.slow
def test_beam_steered_pings_keep_an_azimuth_table_per_ping(test_pings: list, tmp_path: Path) -> None:  # noqa: ANN001
    from sonarmap.store import SurveyWriter, dataset_to_pings, open_survey

    g = test_pings[0].geometry
    steered = g.replace(azimuth_rad=g.azimuth_rad * 0.9)
    pings = [*test_pings[:3], *(p.replace(geometry=steered) for p in test_pings[3:5])]
    out = tmp_path / "s.zarr"
    with SurveyWriter(out, chunk_pings=2) as w:  # the third chunk brings the second table
        w.write(pings)
    ds = open_survey(out)
    assert ds[COORD_AZIMUTH].dims == (DIM_PING, DIM_BEAM)
    for i, p in enumerate(pings):
        np.testing.assert_array_equal(ds[COORD_AZIMUTH].values[i], p.geometry.azimuth_rad)
    assert [q.geometry for q in dataset_to_pings(ds)] == [p.geometry for p in pings]
    assert consolidated_status(out) == "current" and _open_strict(out).returncode == 0


@pytest.mark.slow
def test_appends_keep_consolidated_metadata_in_step(stores: dict[str, Path], test_pings: list,
                                                    tmp_path: Path) -> None:  # noqa: ANN001
    from sonarmap.store import SurveyWriter, open_survey

    out = tmp_path / "a.zarr"
    shutil.copytree(stores["converted"], out)
    w = SurveyWriter(out, mode="a", chunk_pings=1)
    w.add(test_pings[N])  # one chunk written, the writer still open
    assert consolidated_status(out) == "absent"  # never stale while the store changes
    w.close()
    assert consolidated_status(out) == "current"
    r = _open_strict(out)
    assert r.returncode == 0 and int(r.stdout) == N + 1, r.stderr[-2000:]
    _cli(["convert", str(test_pings[N + 1].source), "-o", str(out), "--append", "-q"])
    assert consolidated_status(out) == "current" and int(_open_strict(out).stdout) == N + 2
    assert open_survey(out)[COORD_AZIMUTH].dims == (DIM_BEAM,)


@pytest.mark.slow
def test_added_product_variables_are_consolidated(stores: dict[str, Path], tmp_path: Path) -> None:
    from sonarmap.store import PingVariable, add_ping_variable, write_ping_variable

    out = tmp_path / "v.zarr"
    shutil.copytree(stores["converted"], out)
    add_ping_variable(out, PingVariable("first_range_m", (DIM_BEAM,), units="m"))
    assert consolidated_status(out) == "current"
    write_ping_variable(out, "first_range_m", np.ones((2, 96)), start=0)
    assert consolidated_status(out) == "current"
    code = f"import xarray as xr; print(int(xr.open_zarr({str(out)!r})['first_range_m'].notnull().sum()))"
    r = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and int(r.stdout) == 2 * 96, r.stderr[-2000:]


def test_stale_consolidated_metadata_does_not_mislead_sonarmap(stores: dict[str, Path], tmp_path: Path) -> None:
    from sonarmap.store import open_survey
    from sonarmap.survey import load_products

    for kind, var in (("converted", "intensity"), ("processed", "kld")):
        out = tmp_path / f"{kind}.zarr"
        shutil.copytree(stores[kind], out)
        doc = json.loads((out / "zarr.json").read_text())
        doc["consolidated_metadata"]["metadata"][var]["shape"][0] = 1  # as if the store changed since
        (out / "zarr.json").write_text(json.dumps(doc))
        assert consolidated_status(out) == "stale"
        ds = open_survey(out) if kind == "converted" else load_products(out)
        assert ds.sizes[DIM_PING] == N and ds[var].shape[0] == N, kind


@pytest.mark.slow
def test_info_summarises_a_product_store(stores: dict[str, Path], capsys: pytest.CaptureFixture[str],
                                         test_pings: list) -> None:  # noqa: ANN001
    from sonarmap.survey import flagged_mask, load_products

    capsys.readouterr()
    _cli(["info", str(stores["processed"]), "--json"])
    info = json.loads(capsys.readouterr().out)
    ds = load_products(stores["processed"])
    assert info["format"] == "zarr-products" and info["pings"] == info["pings_done"] == N
    assert info["complete"] is True and info["consolidated"] == "current"
    assert info["flagged"] == int(flagged_mask(ds["flags"].values).sum())
    assert {"range", "kld", "flags", "ping_time"} <= set(info["variables"])
    assert info["time_first_utc"] == str(test_pings[0].datetime64)
    assert info["time_last_utc"] == str(test_pings[N - 1].datetime64)
    assert info["beams"] == test_pings[0].geometry.n_beams and info["bins"] == test_pings[0].geometry.n_bins
    _cli(["info", str(stores["processed"])])  # the table form too
    assert "zarr-products" in capsys.readouterr().out


@pytest.mark.slow
def test_info_summarises_an_interrupted_run(stores: dict[str, Path], tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str], test_pings: list) -> None:  # noqa: ANN001
    """A run stopped before its last chunk: the chunks it did not finish have no data files, and
    ``info`` reports the pings done so far instead of failing on the missing chunks."""
    from sonarmap.store.products import complete_marker, marker_dir

    store = tmp_path / "interrupted.zarr"
    shutil.copytree(stores["processed"], store)  # 4 pings in chunks of 2
    (marker_dir(store) / "00000001.done").unlink()
    complete_marker(store).unlink()
    for arr in store.iterdir():
        if (arr / "c" / "1").exists():
            shutil.rmtree(arr / "c" / "1") if (arr / "c" / "1").is_dir() else (arr / "c" / "1").unlink()
    capsys.readouterr()
    _cli(["info", str(store), "--json"])
    info = json.loads(capsys.readouterr().out)
    assert info["pings"] == N and info["pings_done"] == 2 and info["complete"] is False
    assert info["time_last_utc"] == str(test_pings[1].datetime64)  # the last ping of the done chunk


@pytest.mark.slow
def test_show_renders_a_product_store(stores: dict[str, Path], tmp_path: Path,
                                      test_pings: list) -> None:  # noqa: ANN001
    from sonarmap.survey import load_products, product_ping

    for kind in ("processed", "labels"):
        png = tmp_path / f"{kind}.png"
        _cli(["show", str(stores[kind]), "-o", str(png), "-i", "1"])
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 1000
    raw = product_ping(stores["processed"], 2)  # no labels stored: the source ping
    assert raw.meta["image"] == "raw" and np.array_equal(raw.image, test_pings[2].image)
    seg = product_ping(stores["labels"], 2)
    assert seg.meta["image"] == "labels" and seg.time_ns == test_pings[2].time_ns
    np.testing.assert_array_equal(seg.image, load_products(stores["labels"])["labels"].values[2])
    assert seg.image.max() == 1 and seg.image.min() == 0
    with pytest.raises(DataFormatError, match="no labels stored"):
        product_ping(stores["processed"], 0, image="labels")
    from sonarmap.io import read_pings

    with pytest.raises(DataFormatError, match="product store"):
        list(read_pings(stores["processed"]))


def _old_product_layout(store: Path) -> None:
    """Rewrite a product store as the previous version wrote it: ``echo_range (range_sample)``, no
    index coordinates, no consolidated metadata or ``coordinates`` attribute."""
    import zarr

    from sonarmap.store import checksum_codecs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = zarr.open_group(str(store), mode="r+", use_consolidated=False)
        rng = np.asarray(g[COORD_RANGE][0], np.float64)
        for name in (COORD_RANGE, DIM_RANGE, DIM_BEAM):
            del g[name]
        arr = g.create_array(COORD_RANGE, shape=rng.shape, dtype=rng.dtype, dimension_names=(DIM_RANGE,),
                             attributes={"units": "m"}, **checksum_codecs(), config={"write_empty_chunks": True})
        arr[...] = rng
        del g.attrs["coordinates"]
    doc = json.loads((store / "zarr.json").read_text())
    doc.pop("consolidated_metadata", None)
    (store / "zarr.json").write_text(json.dumps(doc))


@pytest.mark.slow
def test_old_layout_product_store_reads_and_resumes(paths: list[str], stores: dict[str, Path],
                                                    tmp_path: Path) -> None:
    from sonarmap.survey import load_products, process_survey, survey_status

    out = tmp_path / "old.zarr"

    def stop(done: int, total: int) -> None:
        if done >= 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        process_survey(paths, out, workers=0, chunk_size=2, progress=stop)
    _old_product_layout(out)
    assert (out / ".sonarmap" / "chunks").is_dir()  # the old bookkeeping folder inside the store
    assert consolidated_status(out) == "absent" and survey_status(out)["done"] == 1
    part = load_products(out)
    assert part[COORD_RANGE].dims == (DIM_RANGE,) and np.isfinite(part["kld"].values[:2]).all()
    from sonarmap.survey import product_ping

    assert product_ping(out, 1).time_ns == part[DIM_PING].values[1].astype(np.int64)
    with pytest.raises(DataFormatError, match="not processed yet"):
        product_ping(out, 3)
    assert main(["show", str(out), "-o", str(tmp_path / "x.png"), "--image", "neither"]) == 2
    res = process_survey(paths, out, workers=0, chunk_size=2)
    assert res.chunks_skipped == 1 and res.chunks_run == 1 and survey_status(out)["complete"]
    assert consolidated_status(out) == "current" and _open_strict(out).returncode == 0
    a, b = load_products(out), load_products(stores["processed"])
    for name in ("kld", "range", "range_bin"):
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
    for name in ("flags", "source"):
        assert a[name].values.tolist() == b[name].values.tolist(), name
    _cli(["info", str(out), "--json"])


@pytest.mark.slow
def test_old_layout_converted_store_reads_and_appends(stores: dict[str, Path], test_pings: list,
                                                      tmp_path: Path) -> None:  # noqa: ANN001
    import zarr

    from sonarmap.store import SurveyWriter, checksum_codecs, dataset_to_pings, open_survey

    out = tmp_path / "oldc.zarr"
    shutil.copytree(stores["converted"], out)
    with warnings.catch_warnings():  # beam_azimuth (ping_time, beam), as every store had it before
        warnings.simplefilter("ignore")
        g = zarr.open_group(str(out), mode="r+", use_consolidated=False)
        az = np.asarray(g[COORD_AZIMUTH][...])
        attrs = dict(g[COORD_AZIMUTH].attrs)
        del g[COORD_AZIMUTH]
        arr = g.create_array(COORD_AZIMUTH, shape=(N, az.size), chunks=(16, az.size), dtype=az.dtype,
                             dimension_names=(DIM_PING, DIM_BEAM), attributes=attrs, **checksum_codecs(),
                             config={"write_empty_chunks": True})
        arr[...] = np.broadcast_to(az, (N, az.size))
    doc = json.loads((out / "zarr.json").read_text())
    doc.pop("consolidated_metadata")
    (out / "zarr.json").write_text(json.dumps(doc))
    back = list(dataset_to_pings(open_survey(out)))
    assert [p.time_ns for p in back] == [p.time_ns for p in test_pings[:N]]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(back, test_pings, strict=False))
    with SurveyWriter(out, mode="a") as w:
        w.add(test_pings[N])
    ds = open_survey(out)
    assert ds[COORD_AZIMUTH].dims == (DIM_PING, DIM_BEAM) and ds[COORD_AZIMUTH].shape == (N + 1, az.size)
    np.testing.assert_array_equal(ds[COORD_AZIMUTH].values[N], test_pings[N].geometry.azimuth_rad)
    assert consolidated_status(out) == "current" and _open_strict(out).returncode == 0


def test_geometries_in_attributes_read_back_in_both_formats(stores: dict[str, Path]) -> None:
    """The raw-ping store records each geometry with its azimuth source (keys sorted), a product
    store's ``source_geometry`` the geometry's dict; one reader gives the geometry of either."""
    import dataclasses

    from sonarmap.geometry import preset
    from sonarmap.store import inspect_products, store_geometry
    from sonarmap.store.metadata import geometry_from_json, geometry_json, read_root_attrs

    g = dataclasses.replace(preset("didson-hf"), azimuth_source="preset:didson-hf")  # as the readers give it
    raw, prod = geometry_json(g), geometry_json(g, with_source=False)
    assert json.loads(raw)["azimuth_source"] == g.azimuth_source and "azimuth_source" not in json.loads(prod)
    assert geometry_from_json(raw, "test") == g and geometry_from_json(raw, "test").azimuth_source == g.azimuth_source
    back = geometry_from_json(prod, "test")
    assert np.array_equal(back.azimuth_rad, g.azimuth_rad) and back.azimuth_source == "table"
    attrs = read_root_attrs(stores["processed"])
    assert attrs is not None and attrs["source_geometry"] == geometry_json(
        geometry_from_json(attrs["source_geometry"], "test"), with_source=False)
    st, _ = inspect_products(stores["processed"])
    assert store_geometry(st).n_beams == len(json.loads(attrs["source_geometry"])["azimuths"])
