"""PNG/BMP + JSON ping I/O on the real DIDSON recordings."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import DataFormatError, GeometryError, InputError
from sonarmap.geometry import preset
from sonarmap.io import detect_format, read_ping, read_pings
from sonarmap.io.pngjson import (
    find_png_pings,
    iter_png_pings,
    read_image_file,
    read_png_ping,
    time_ns_from_stem,
    write_png_ping,
)
from sonarmap.ping import Ping


def test_load_all_126_real_pings(test_ping_paths: list[Path], background_paths: list[Path]) -> None:
    pings = list(read_pings([*test_ping_paths, *background_paths]))
    assert len(pings) == 126
    for p in pings:
        assert p.image.dtype == np.float32 and p.shape == (512, 96)
        assert 0.0 <= p.image.min() and p.image.max() <= 1.0
        assert p.geometry.azimuth_source == "preset:didson-hf"
    # sorted by time across both folders: test pings precede the background set
    times = [p.time_ns for p in pings]
    assert times == sorted(times)
    # 8-bit values map exactly to k/255 and about 60 % of the background pixels are zero
    img = pings[-1].image
    assert np.allclose(img * 255, np.rint(img * 255), atol=1e-4)
    zero = np.mean([np.mean(p.image == 0) for p in pings[10:]])
    assert 0.55 < zero < 0.7


def test_sidecar_geometry_is_named_after_the_sonar_not_the_ping(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    """A sidecar without ``name`` names its sonar after the preset whose azimuth table it takes
    (the DIDSON's), else ``sonar``; never after the ping's file (its time stamp), which reports,
    ``info`` and the product stores would then show as the sonar's name."""
    assert {p.geometry.name for p in read_pings(test_ping_paths[:3])} == {"didson-hf"}
    g = preset("oculus-m750d-like")
    out = write_png_ping(Ping(np.zeros(g.shape, np.float32), g, time_ns=7_000_000_000), tmp_path)
    side = tmp_path / "7000000.json"
    d = json.loads(side.read_text())
    assert d.pop("name") == "oculus-m750d-like" and len(d["azimuths"]) == g.n_beams
    side.write_text(json.dumps(d))
    assert read_png_ping(out).geometry.name == "sonar"  # its own azimuths, no name
    d["name"] = "my-sonar"
    side.write_text(json.dumps(d))
    assert read_png_ping(out).geometry.name == "my-sonar"


def test_time_stamps_from_file_names() -> None:
    assert time_ns_from_stem("1468966347175925_raw") == 1468966347175925000
    assert time_ns_from_stem("1468966347") == 1468966347 * 10**9
    assert time_ns_from_stem("1468966347175") == 1468966347175 * 10**6
    assert time_ns_from_stem("ping_3") is None


def test_directory_iteration_is_sorted_and_lazy(didson_dir: Path) -> None:
    it = iter_png_pings(didson_dir / "test")
    first = next(it)
    assert first.source.endswith("1468966347175925_raw.png")
    rest = list(it)
    assert len(rest) == 9
    assert [p.time_ns for p in rest] == sorted(p.time_ns for p in rest)
    glob_hits = find_png_pings(str(didson_dir / "test" / "*_raw.png"))
    assert len(glob_hits) == 10


def test_write_read_round_trip_lossless(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    p = read_png_ping(test_ping_paths[3])
    out = write_png_ping(p, tmp_path)
    assert out.name == test_ping_paths[3].name
    back = read_png_ping(out)
    np.testing.assert_array_equal(back.image, p.image)
    assert back.time_ns == p.time_ns and back.geometry == p.geometry
    # byte-identical pixel data to the original PNG
    from PIL import Image

    a = np.asarray(Image.open(test_ping_paths[3]))
    b = np.asarray(Image.open(out))
    np.testing.assert_array_equal(a, b)


def test_eight_bit_levels_map_to_float32_k_times_float32_one_255th(tmp_path: Path) -> None:
    from PIL import Image

    levels = np.arange(256, dtype=np.uint8).reshape(16, 16)
    Image.fromarray(levels, mode="L").save(tmp_path / "levels.png")
    got = read_image_file(tmp_path / "levels.png")
    want = np.arange(256, dtype=np.float32).reshape(16, 16) * np.float32(1.0 / 255.0)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))  # bit for bit
    assert got[0, 0] == 0.0 and got[-1, -1] == 1.0


def test_sixteen_bit_round_trip(tmp_path: Path) -> None:
    g = preset("didson-hf")
    rng = np.random.default_rng(1)
    img = rng.random(g.shape, dtype=np.float32)
    out = write_png_ping(Ping(img, g, time_ns=1_000_000_000), tmp_path, bit_depth=16)
    back = read_png_ping(out)
    assert np.abs(back.image - img).max() <= 0.5 / 65535 + 1e-7


def test_json_path_finds_image_and_bmp_needs_geometry(didson_dir: Path) -> None:
    p = read_png_ping(didson_dir / "test" / "1468966347175925.json")
    assert p.source.endswith("_raw.png")
    bmp = didson_dir / "extra" / "frame_2014.bmp"
    assert detect_format(bmp) == "pngjson"
    with pytest.raises(DataFormatError, match="no sidecar JSON"):
        read_png_ping(bmp)
    q = read_ping(bmp, geometry="didson-hf")
    assert q.shape == (512, 96) and q.time_ns == 0


def test_corrupt_and_mismatched_inputs(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    src = test_ping_paths[0]
    trunc = tmp_path / "1468966347175925_raw.png"
    trunc.write_bytes(src.read_bytes()[:300])
    shutil.copy(src.with_name("1468966347175925.json"), tmp_path)
    with pytest.raises(DataFormatError, match="1468966347175925_raw.png"):
        read_png_ping(trunc)
    bad = tmp_path / "x.png"
    bad.write_bytes(b"not an image at all")
    with pytest.raises(DataFormatError, match="x.png: not a PNG/BMP image"):
        read_png_ping(bad, geometry="didson-hf")
    with pytest.raises(GeometryError, match="does not match geometry 'aris3000-128'"):
        read_png_ping(src, geometry="aris3000-128")
    side = tmp_path / "1468966347175925.json"
    d = json.loads(side.read_text())
    d["num_bins"] = 500
    side.write_text(json.dumps(d))
    trunc.write_bytes(src.read_bytes())
    with pytest.raises(GeometryError, match=r"\(512, 96\) does not match"):
        read_png_ping(trunc)
    with pytest.raises(DataFormatError, match="no such file"):
        list(read_pings(tmp_path / "missing.png"))


def test_ping_validation() -> None:
    g = preset("didson-hf")
    with pytest.raises(GeometryError, match="shape"):
        Ping(np.zeros((10, 96), np.float32), g)
    bad = np.zeros(g.shape, np.float32)
    bad[3, 4] = np.nan
    with pytest.raises(InputError, match="NaN"):
        Ping(bad, g)
    with pytest.raises(InputError, match="numeric"):
        Ping(np.zeros(g.shape, dtype=object), g)
    p = Ping(np.zeros(g.shape, np.uint8), g)
    assert p.image.dtype == np.float32


def test_intensity_scale_in_sidecar_is_applied(tmp_path: Path) -> None:
    g = preset("didson-hf")
    img = np.zeros(g.shape, np.float32)
    img[10, 10] = 2.5  # above 1: stored as image / scale
    p = Ping(img / np.float32(2.5), g, time_ns=5_000_000_000)
    out = write_png_ping(p, tmp_path, extra={"intensity_scale": 2.5})
    back = read_png_ping(out)
    assert back.image[10, 10] == pytest.approx(2.5)
    side = tmp_path / "5000000_raw.png"
    assert side.exists()
    d = json.loads((tmp_path / "5000000.json").read_text())
    d["intensity_scale"] = -1
    (tmp_path / "5000000.json").write_text(json.dumps(d))
    with pytest.raises(DataFormatError, match="intensity_scale must be a positive number"):
        read_png_ping(out)


def test_outputs_follow_umask(tmp_path: Path) -> None:
    import os

    old = os.umask(0o022)
    try:
        out = write_png_ping(Ping(np.zeros(preset("didson-hf").shape, np.float32), preset("didson-hf")), tmp_path)
    finally:
        os.umask(old)
    assert out.stat().st_mode & 0o777 == 0o644
