"""Survey dataset (xarray/zarr): data model, lossless round trips, appends, extra variables, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sonarmap.cli import main
from sonarmap.errors import DataFormatError, InputError
from sonarmap.io import detect_format, read_pings, zarrstore
from sonarmap.datamodel import COORD_AZIMUTH, COORD_RANGE, DIM_BEAM, DIM_PING, DIM_RANGE, VAR_INTENSITY
from sonarmap.store import (
    PingVariable,
    SurveyWriter,
    add_ping_variable,
    dataset_to_pings,
    open_survey,
    pings_to_dataset,
    write_ping_variable,
    write_survey,
)
from sonarmap.ping import Ping, Pose



def _same(a: Ping, b: Ping) -> None:
    assert np.array_equal(a.image, b.image)
    assert a.geometry == b.geometry and a.geometry.window == b.geometry.window
    assert a.time_ns == b.time_ns


def test_data_model(aris_pings: list[Ping]) -> None:
    ds = pings_to_dataset(aris_pings[:2])
    assert ds[VAR_INTENSITY].dims == (DIM_PING, DIM_RANGE, DIM_BEAM)
    assert ds[COORD_RANGE].dims == (DIM_PING, DIM_RANGE) and ds[COORD_RANGE].attrs["units"] == "m"
    assert ds[COORD_AZIMUTH].attrs["units"] == "rad" and "long_name" in ds[VAR_INTENSITY].attrs
    assert ds.attrs["Conventions"] == "CF-1.8"
    assert np.array_equal(ds[COORD_RANGE].values[0], aris_pings[0].geometry.range_m)
    assert ds[DIM_PING].values[0] == aris_pings[0].datetime64
    assert ds["meta_compass_heading_deg"].attrs["units"] == "degree"
    with pytest.raises(InputError, match="differs from the survey"):
        pings_to_dataset([aris_pings[0], Ping(image=np.zeros((3, 3), np.float32),
                                              geometry=aris_pings[0].geometry.replace(
                                                  azimuth_rad=[-0.1, 0, 0.1], range_m=[1, 2, 3]))])


@pytest.mark.slow  # over a second in the fast subset
def test_convert_reopen_lossless(aris_pings: list[Ping], data_dir: Path, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    assert write_survey(iter(aris_pings), store, chunk_pings=4) == 6
    assert detect_format(store) == "zarr" and zarrstore.count_pings(store) == 6
    ds = open_survey(store)
    assert ds[VAR_INTENSITY].chunks[0] == (4, 2)  # chunked along ping_time
    back = list(read_pings(store))
    for a, b in zip(aris_pings, back, strict=True):
        _same(a, b)
        assert b.source == str(data_dir / "aris" / "sample.aris")
        assert {k: v for k, v in a.meta.items() if k != "format"} == b.meta
        assert type(b.meta["frame_index"]) is int and type(b.meta["large_lens"]) is bool
    s = zarrstore.summary(store)
    assert s["pings"] == 6 and s["image_shape"] == (2000, 48) and s["name"] == "aris-telephoto-48"


@pytest.mark.slow
def test_append_poses_and_atomic_failure(aris_pings: list[Ping], tmp_path: Path) -> None:
    store = tmp_path / "a.zarr"
    posed = [p.replace(pose=Pose(position_m=[i, 2, 3], orientation_xyzw=[0, 0, 0, 1])) for i, p in enumerate(aris_pings)]
    write_survey(posed[:2], store)
    write_survey(posed[2:5], store, append=True, chunk_pings=2)
    back = list(dataset_to_pings(open_survey(store)))
    assert len(back) == 5
    assert [b.pose.position_m[0] for b in back] == [0, 1, 2, 3, 4]
    # a failing write leaves the existing store untouched
    with pytest.raises(RuntimeError), SurveyWriter(store, chunk_pings=2) as w:
        w.add(aris_pings[0])
        w.add(aris_pings[1])
        raise RuntimeError("crash")
    assert open_survey(store).sizes[DIM_PING] == 5
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.slow  # over a second in the fast subset
def test_interrupted_append_is_detected_and_repaired(aris_pings: list[Ping], tmp_path: Path) -> None:
    import zarr

    store = tmp_path / "i.zarr"
    write_survey(aris_pings[:4], store, chunk_pings=2)
    g = zarr.open_group(str(store), mode="r+")
    g[VAR_INTENSITY].resize((5, 2000, 48))  # as if an append died after writing one array
    with pytest.raises(DataFormatError, match="repair=True"):
        open_survey(store)
    assert open_survey(store, repair=True).sizes[DIM_PING] == 4


@pytest.mark.slow  # over a second in the fast subset
def test_extra_per_ping_variables(aris_pings: list[Ping], tmp_path: Path) -> None:
    store = tmp_path / "x.zarr"
    var = PingVariable("first_return_range_m", ("beam",), units="m", long_name="First return range")
    with SurveyWriter(store, chunk_pings=2, extra_variables=[var]) as w:
        for i, p in enumerate(aris_pings[:3]):
            w.add(p, first_return_range_m=np.full(48, float(i)))
    ds = open_survey(store)
    assert ds[var.name].dims == (DIM_PING, DIM_BEAM) and ds[var.name].attrs["units"] == "m"
    assert ds[var.name].values[:, 0].tolist() == [0.0, 1.0, 2.0]
    # a later stage adds its product to the existing store, region by region
    flag = PingVariable("n_detections", (), dtype="int32", fill_value=-1)
    add_ping_variable(store, flag)
    add_ping_variable(store, flag)  # idempotent
    write_ping_variable(store, "n_detections", [7], start=1)
    ds = open_survey(store)
    assert ds["n_detections"].values.tolist() == [-1, 7, -1]
    assert json.loads(ds.attrs["sonarmap_geometries"])  # attributes survive the additions
    with pytest.raises(InputError, match="declare it"):
        write_ping_variable(store, "nope", [1], start=0)


def test_not_a_store(tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match="not a zarr survey store"):
        open_survey(tmp_path)


@pytest.mark.slow
def test_cli_convert_and_info(data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "survey.zarr"
    assert main(["convert", str(data_dir / "oculus" / "three_pings_8bit.raw"), "-o", str(out)]) == 0
    cap = capsys.readouterr()
    assert "wrote 3 pings" in cap.err and cap.out == ""  # a message: stderr
    assert main(["convert", str(data_dir / "oculus" / "one_ping_8bit.raw"), "-o", str(out), "--append", "--no-progress"]) == 0
    assert zarrstore.count_pings(out) == 4
    a = list(read_pings([data_dir / "oculus" / "three_pings_8bit.raw", data_dir / "oculus" / "one_ping_8bit.raw"]))
    for x, y in zip(a, read_pings(out), strict=True):
        _same(x, y)
    bag = tmp_path / "s.bag"
    assert main(["convert", str(out), "-o", str(bag), "--no-progress"]) == 0
    assert main(["info", "--json", str(bag)]) == 0
    text = capsys.readouterr().out
    info = json.loads(text[text.index("{"):])
    assert info["format"] == "rosbag" and info["pings"] == 4
    # mixed image shapes: clear one-line error, exit code 1, nothing written
    bad = tmp_path / "mixed.zarr"
    assert main(["convert", str(data_dir / "aris" / "sample.aris"), str(data_dir / "oculus" / "one_ping_8bit.raw"),
                 "-o", str(bad), "--no-progress"]) == 1
    assert "differs from the survey" in capsys.readouterr().err
    assert not bad.exists()


@pytest.mark.slow  # over a second in the fast subset
def test_append_pings_to_store_with_products(aris_pings: list[Ping], tmp_path: Path) -> None:
    """Pings appended after a processing stage added a variable get that variable's fill value."""
    store = tmp_path / "p.zarr"
    write_survey(aris_pings[:2], store)
    add_ping_variable(store, PingVariable("label_count", (), dtype="int16", fill_value=-1))
    write_ping_variable(store, "label_count", [3, 4], start=0)
    write_survey(aris_pings[2:4], store, append=True)
    assert open_survey(store)["label_count"].values.tolist() == [3, 4, -1, -1]


def test_corrupt_store(aris_pings: list[Ping], tmp_path: Path) -> None:
    store = tmp_path / "c.zarr"
    write_survey(aris_pings[:3], store, chunk_pings=2)
    chunk = next(p for p in (store / VAR_INTENSITY).rglob("*") if p.is_file() and p.name != "zarr.json")
    chunk.write_bytes(chunk.read_bytes()[:50])
    with pytest.raises(DataFormatError, match=r"c\.zarr: cannot read pings 0-1"):
        list(read_pings(store))
    (store / "zarr.json").write_text("{ not json")
    with pytest.raises(DataFormatError, match=r"c\.zarr"):
        open_survey(store)
