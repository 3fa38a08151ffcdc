"""Hardening of PNG/BMP + JSON sidecar pings and geometry JSON against hostile or broken input.

Regression tests for the fuzzing reproducers of the "Hardening" issue (each used to escape as a
builtin exception, hang, or exhaust memory), the CLI's one-line error for each, and a seeded
mini-fuzz over a real DIDSON sidecar and PNG.  Real data is only read from ``../shared/data``;
mutated copies live in ``tmp_path``.  Anything that could hang runs under a SIGALRM deadline;
anything that could allocate without bound runs in a subprocess with a 2 GiB address-space limit.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import textwrap
import warnings
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from guards import deadline

from sonarmap.cli import main
from sonarmap.errors import DataFormatError, GeometryError, SonarmapError
from sonarmap.geometry import (
    MAX_BEAMS,
    MAX_BINS,
    SINGLE_BEAM_WIDTH_RAD,
    GeometryWarning,
    SonarGeometry,
    as_geometry,
    load_geometry,
    save_geometry,
    uniform_azimuths,
)
from sonarmap.io import detect_format, expand_inputs, read_pings
from sonarmap._files import MAX_SIDECAR_BYTES
from sonarmap.io.pngjson import MAX_IMAGE_PIXELS, read_png_ping, write_png_ping
from sonarmap.ping import Ping

STEM = "1468966347175925"  # the first paper test ping
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------- helpers

@contextlib.contextmanager
def _memory_cap(extra_bytes: int = 2 * 1024**3) -> Iterator[None]:
    """Cap this process's address space at its current size + ``extra_bytes`` for the block.

    A regression that allocates without bound (``num_bins: 1e9`` once allocated ~8 GB twice) then
    raises MemoryError - a test failure - instead of getting a shared machine's workers OOM-killed.
    """
    import resource

    status = Path("/proc/self/status").read_text()
    vm_kib = int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmSize:")))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = vm_kib * 1024 + extra_bytes
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _real_ping(didson_dir: Path) -> tuple[dict[str, Any], bytes]:
    """The first DIDSON test ping's sidecar (decoded) and PNG bytes."""
    side = didson_dir / "test" / f"{STEM}.json"
    png = didson_dir / "test" / f"{STEM}_raw.png"
    return json.loads(side.read_text()), png.read_bytes()


def _write_ping(
    directory: Path, png: bytes, sidecar: dict[str, Any] | str | bytes | None, stem: str = STEM,
    suffix: str = "_raw.png",
) -> Path:
    """Write an image and its sidecar (a dict is JSON-encoded; text/bytes are written as is)."""
    directory.mkdir(parents=True, exist_ok=True)
    img = directory / f"{stem}{suffix}"
    img.write_bytes(png)
    if sidecar is not None:
        side = directory / f"{stem}.json"
        if isinstance(sidecar, dict):
            side.write_text(json.dumps(sidecar))
        elif isinstance(sidecar, str):
            side.write_text(sidecar)
        else:
            side.write_bytes(sidecar)
    return img


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _with_ihdr(png: bytes, width: int, height: int, bit_depth: int = 8, colour: int = 0,
               interlace: int = 0) -> bytes:
    """``png`` with its IHDR rewritten (valid CRC), keeping the pixel data."""
    assert png[12:16] == b"IHDR"
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour, 0, 0, interlace)
    return png[:8] + _png_chunk(b"IHDR", ihdr) + png[33:]


def _header_only_png(width: int, height: int) -> bytes:
    """A tiny PNG whose header claims ``width`` x ``height`` pixels (a decompression bomb's header)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr)
            + _png_chunk(b"IDAT", zlib.compress(b"\0" * 1024)) + _png_chunk(b"IEND", b""))


def _bmp_bytes(png: bytes) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    with Image.open(io.BytesIO(png)) as im:
        im.save(buf, format="BMP")
    return buf.getvalue()


def _error_lines(capsys: pytest.CaptureFixture[str]) -> list[str]:
    return capsys.readouterr().err.strip("\n").splitlines()


def _assert_one_clean_cli_error(capsys: pytest.CaptureFixture[str], argv: list[str], *needles: str) -> str:
    capsys.readouterr()
    with deadline(20.0), _memory_cap():
        rc = main(argv)
    lines = _error_lines(capsys)
    assert rc == 1, lines
    assert len(lines) == 1, lines
    assert lines[0].startswith("sonarmap: error:"), lines
    assert "internal error" not in lines[0]
    for n in needles:
        assert n in lines[0], lines
    return lines[0]


# ---------------------------------------------------------------------- sidecar field reproducers
SIDECAR_REPRODUCERS = [
    pytest.param({"num_beams": 0}, "field 'num_beams' must be between 1 and 4096", id="num_beams=0"),
    pytest.param({"num_beams": False}, "field 'num_beams' must be an integer, got False", id="num_beams=False"),
    pytest.param({"num_beams": 0.5}, "field 'num_beams' must be an integer, got 0.5", id="num_beams=0.5"),
    pytest.param({"azimuths": 5}, "field 'azimuths' must be a list of numbers, got 5", id="azimuths=5"),
    pytest.param({"num_bins": math.nan}, "field 'num_bins' must be an integer, got nan", id="num_bins=nan"),
    pytest.param({"num_bins": math.inf}, "field 'num_bins' must be an integer, got inf", id="num_bins=inf"),
    pytest.param({"num_bins": 1e308}, "field 'num_bins' must be between 1 and 65536", id="num_bins=1e308"),
    pytest.param({"num_bins": 1e9}, "field 'num_bins' must be between 1 and 65536", id="num_bins=1e9"),
    pytest.param({"fov": 0}, "field 'fov' must be in (0, 2 pi]", id="fov=0"),
    pytest.param({"psf": [True] * 96}, "field 'psf' entry 0 must be a number, got True", id="psf-bools"),
    pytest.param({"taper": [1.0] * 95}, "taper: length 95 does not match 96 beams", id="taper-short"),
    pytest.param({"noise": -1e-3}, "noise: 1/SNR must be >= 0", id="noise<0"),
    pytest.param({"max_range": 1e6}, "max_range: must be at most 25000 m", id="max_range=1e6"),
    pytest.param({"min_range": 12.0}, "must exceed min_range", id="min>max"),
]


@pytest.mark.parametrize("change,message", SIDECAR_REPRODUCERS)
def test_sidecar_field_reproducers_are_geometry_errors(
    tmp_path: Path, didson_dir: Path, change: dict[str, Any], message: str
) -> None:
    side, png = _real_ping(didson_dir)
    side.update(change)
    img = _write_ping(tmp_path, png, side)
    with _memory_cap(), pytest.raises(GeometryError) as ei:
        read_png_ping(img)
    msg = str(ei.value)
    assert msg.startswith(f"{tmp_path / (STEM + '.json')}: "), msg
    assert message in msg and "\n" not in msg and len(msg) < 300, msg


def test_azimuth_table_checked_element_by_element(tmp_path: Path, didson_dir: Path) -> None:
    side, png = _real_ping(didson_dir)
    az = json.loads((didson_dir / "didson.json").read_text())["azimuths"]
    for bad, message in [
        (az[::-1], "strictly increasing"),
        (az[:95], "'azimuths' has 95 entries but num_beams is 96"),
        ([*az[:10], "x", *az[11:]], "field 'azimuths' entry 10 must be a number, got 'x'"),
        ([*az[:10], [0.1], *az[11:]], "field 'azimuths' entry 10 must be a number, got a list of 1 items"),
        ([*az[:10], math.nan, *az[11:]], "field 'azimuths' entry 10 must be finite, got nan"),
        ([*az[:10], 10**400, *az[11:]], "entry 10 must be a finite number, got an integer of about 401 digits"),
    ]:
        img = _write_ping(tmp_path, png, {**side, "azimuths": bad})
        with pytest.raises(GeometryError, match=message.replace("(", r"\(").replace("[", r"\[")):
            read_png_ping(img)
    good = read_png_ping(_write_ping(tmp_path, png, {**side, "azimuths": az}))
    np.testing.assert_array_equal(good.geometry.azimuth_rad, az)


def test_deeply_nested_json_is_a_format_error(tmp_path: Path, didson_dir: Path) -> None:
    _, png = _real_ping(didson_dir)
    img = _write_ping(tmp_path, png, "[" * 100000)
    with pytest.raises(DataFormatError, match=rf"{STEM}\.json: invalid JSON: .*nested too deeply"):
        read_png_ping(img)
    geo = tmp_path / "deep.json"
    geo.write_text('{"psf": ' + "[" * 100000)
    with pytest.raises(DataFormatError, match=r"deep\.json: invalid JSON"):
        load_geometry(geo)


def test_integer_literal_beyond_python_digit_limit_is_a_format_error(tmp_path: Path, didson_dir: Path) -> None:
    side, png = _real_ping(didson_dir)
    text = json.dumps({**side, "num_bins": 7}).replace('"num_bins": 7', '"num_bins": ' + "9" * 5000)
    img = _write_ping(tmp_path, png, text)
    with pytest.raises(DataFormatError, match=rf"{STEM}\.json: invalid JSON: an integer has more than \d+ digits"):
        read_png_ping(img)


def test_oversized_sidecar_is_refused_without_reading(tmp_path: Path, didson_dir: Path) -> None:
    _, png = _real_ping(didson_dir)
    img = _write_ping(tmp_path, png, None)
    with open(tmp_path / f"{STEM}.json", "wb") as fh:
        fh.truncate(MAX_SIDECAR_BYTES + 1)  # sparse: the size alone must refuse it
    with pytest.raises(DataFormatError, match="more than the .* allowed"):
        read_png_ping(img)


_LIMITED_CHILD = textwrap.dedent(
    """
    import contextlib, io, json, resource, sys, warnings
    limit = 2 * 1024 ** 3
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    warnings.simplefilter("ignore")
    from sonarmap.errors import SonarmapError

    def attempt(fn):
        try:
            fn()
        except SonarmapError as exc:
            return [type(exc).__name__, str(exc)]
        except BaseException as exc:  # MemoryError under the limit means "would allocate"
            return ["ESCAPED " + type(exc).__name__, str(exc)[:300]]
        return ["ok", ""]

    def cli(argv):
        from sonarmap.cli import main
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            rc = main(argv)
        return [rc, err.getvalue().splitlines()]
    """
)


def _run_limited(body: str) -> dict[str, Any]:
    """Run ``body`` (after :data:`_LIMITED_CHILD`) in a memory-limited child; it prints JSON."""
    proc = subprocess.run(
        [sys.executable, "-c", _LIMITED_CHILD + textwrap.dedent(body)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # starts a child process
def test_num_bins_1e9_allocates_nothing(tmp_path: Path, didson_dir: Path) -> None:
    """``num_bins: 1e9`` used to allocate ~8 GB twice; now refused before any allocation."""
    side, png = _real_ping(didson_dir)
    img = _write_ping(tmp_path, png, {**side, "num_bins": 1e9})
    out = _run_limited(
        f"""
        from sonarmap.geometry import SonarGeometry
        from sonarmap.io.pngjson import read_png_ping
        print(json.dumps({{
            "read": attempt(lambda: read_png_ping({str(img)!r})),
            "window": attempt(lambda: SonarGeometry.from_window(
                min_range_m=1.0, max_range_m=2.0, n_bins=1e9, n_beams=96, fov_rad=0.5)),
            "cli": cli(["info", {str(img)!r}]),
        }}))
        """
    )
    assert out["read"][0] == "GeometryError" and "num_bins" in out["read"][1], out
    assert out["window"][0] == "GeometryError" and "num_bins" in out["window"][1], out
    rc, lines = out["cli"]
    assert rc == 1 and len(lines) == 1 and lines[0].startswith("sonarmap: error:"), out


# ---------------------------------------------------------------------- image reproducers
@pytest.mark.parametrize("width,height", [(30000, 30000), (10000, 10000), (2**31 - 1, 2**31 - 1)])
def test_decompression_bomb_header_is_refused_before_decoding(
    tmp_path: Path, width: int, height: int
) -> None:
    img = tmp_path / "bomb.png"
    img.write_bytes(_header_only_png(width, height))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no DecompressionBombWarning either
        with pytest.raises(DataFormatError, match=rf"bomb\.png: image header gives {width} x {height}"):
            read_png_ping(img, geometry="didson-hf")
    assert width * height > MAX_IMAGE_PIXELS


def test_bmp_header_size_is_checked_too(tmp_path: Path, didson_dir: Path) -> None:
    _, png = _real_ping(didson_dir)
    bmp = bytearray(_bmp_bytes(png))
    assert int.from_bytes(bmp[14:18], "little") == 40
    bmp[18:26] = struct.pack("<ii", 40000, -40000)
    img = tmp_path / "big.bmp"
    img.write_bytes(bytes(bmp))
    with pytest.raises(DataFormatError, match="image header gives 40000 x 40000"):
        read_png_ping(img, geometry="didson-hf")


def test_sidecar_shape_is_checked_from_the_header_before_pixels(tmp_path: Path, didson_dir: Path) -> None:
    side, png = _real_ping(didson_dir)
    broken_pixels = png[:33] + _png_chunk(b"IDAT", b"definitely not zlib") + _png_chunk(b"IEND", b"")
    img = _write_ping(tmp_path, broken_pixels, {**side, "num_bins": 500})
    # the mismatch is found from IHDR: the corrupt pixel data is never decoded
    with pytest.raises(GeometryError, match=r"image shape \(512, 96\) does not match geometry .*\(500, 96\)"):
        read_png_ping(img)
    img = _write_ping(tmp_path, broken_pixels, side)
    with pytest.raises(DataFormatError, match="corrupt or truncated image"):
        read_png_ping(img)


def test_truncated_png_is_an_error_not_a_partly_zero_image(tmp_path: Path, didson_dir: Path) -> None:
    from PIL import ImageFile

    assert ImageFile.LOAD_TRUNCATED_IMAGES is False
    side, png = _real_ping(didson_dir)
    full = read_png_ping(didson_dir / "test" / f"{STEM}_raw.png").image
    iend = png.rindex(b"IEND") - 4
    for cut in [*range(8, iend - 16, 397), *range(iend - 16, len(png))]:
        img = _write_ping(tmp_path, png[:cut], side)
        if cut < iend - 16:  # pixel data missing: always an error
            with pytest.raises(DataFormatError, match=rf"{STEM}_raw\.png: corrupt or truncated image"):
                read_png_ping(img)
            continue
        # only the zlib checksum, IDAT CRC or IEND missing: an error, or the complete exact image
        try:
            got = read_png_ping(img).image
        except DataFormatError:
            continue
        np.testing.assert_array_equal(got, full)


def test_other_image_formats_named_png_are_refused(tmp_path: Path, didson_dir: Path) -> None:
    from PIL import Image

    _, png = _real_ping(didson_dir)
    buf = io.BytesIO()
    with Image.open(io.BytesIO(png)) as im:
        im.save(buf, format="TIFF")
    img = tmp_path / "tiff.png"
    img.write_bytes(buf.getvalue())
    with pytest.raises(DataFormatError, match=r"tiff\.png: not a PNG/BMP image"):
        read_png_ping(img, geometry="didson-hf")


# ---------------------------------------------------------------------- non-regular files
def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def test_fifo_image_sidecar_and_geometry_fail_fast(tmp_path: Path, didson_dir: Path) -> None:
    side, png = _real_ping(didson_dir)
    a = tmp_path / "a"
    a.mkdir()
    (a / f"{STEM}.json").write_text(json.dumps(side))
    fifo_img = _fifo(a / f"{STEM}_raw.png")
    b = tmp_path / "b"
    b.mkdir()
    (b / f"{STEM}_raw.png").write_bytes(png)
    fifo_side = _fifo(b / f"{STEM}.json")
    fifo_geo = _fifo(tmp_path / "geometry.json")
    fifo_any = _fifo(tmp_path / "x.aris")
    calls: list[tuple[Callable[[], object], str]] = [
        (lambda: read_png_ping(fifo_img), "image is a FIFO"),
        (lambda: read_png_ping(a / f"{STEM}.json"), "image is a FIFO"),
        (lambda: list(read_pings(a)), "image is a FIFO"),  # a directory listing holding a FIFO ping
        (lambda: read_png_ping(b / f"{STEM}_raw.png"), "sidecar JSON is a FIFO"),
        (lambda: list(read_pings(b)), "sidecar JSON is a FIFO"),
        (lambda: list(read_pings(fifo_side)), "is a FIFO"),
        (lambda: load_geometry(fifo_geo), "geometry JSON is a FIFO"),
        (lambda: as_geometry(str(fifo_geo)), "geometry JSON is a FIFO"),
        (lambda: read_png_ping(b / f"{STEM}_raw.png", geometry=fifo_geo), "geometry JSON is a FIFO"),
        (lambda: detect_format(fifo_any), "is a FIFO"),
        (lambda: expand_inputs(str(tmp_path / "*.aris")), "is a FIFO"),
    ]
    for fn, message in calls:
        with deadline(10.0), _memory_cap(), pytest.raises(DataFormatError, match=message):
            fn()


def test_fifo_pings_in_cli_info_and_ranges(
    tmp_path: Path, didson_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    side, _ = _real_ping(didson_dir)
    (tmp_path / f"{STEM}.json").write_text(json.dumps(side))
    fifo_img = _fifo(tmp_path / f"{STEM}_raw.png")
    fifo_json = _fifo(tmp_path / "x.json")
    for path in (fifo_img, fifo_json):
        _assert_one_clean_cli_error(capsys, ["info", str(path)], "FIFO")
        out = tmp_path / "ranges.csv"
        _assert_one_clean_cli_error(capsys, ["ranges", str(path), "-o", str(out)], "FIFO")
    _assert_one_clean_cli_error(capsys, ["info", str(tmp_path)], "FIFO")


@pytest.mark.slow  # starts a child process
def test_symlinks_to_dev_zero_are_refused(tmp_path: Path, didson_dir: Path) -> None:
    """In a memory-limited child: reading /dev/zero to the end would exhaust memory."""
    side, png = _real_ping(didson_dir)
    a = tmp_path / "a"
    a.mkdir()
    (a / f"{STEM}.json").write_text(json.dumps(side))
    (a / f"{STEM}_raw.png").symlink_to("/dev/zero")
    b = tmp_path / "b"
    b.mkdir()
    (b / f"{STEM}_raw.png").write_bytes(png)
    (b / f"{STEM}.json").symlink_to("/dev/zero")
    geo = tmp_path / "zero.json"
    geo.symlink_to("/dev/zero")
    out = _run_limited(
        f"""
        from sonarmap.geometry import load_geometry
        from sonarmap.io import detect_format, read_pings
        from sonarmap.io.pngjson import read_png_ping
        a, b, geo = {str(a)!r}, {str(b)!r}, {str(geo)!r}
        print(json.dumps({{
            "image": attempt(lambda: read_png_ping(a + "/{STEM}_raw.png")),
            "image_dir": attempt(lambda: list(read_pings(a))),
            "sidecar": attempt(lambda: read_png_ping(b + "/{STEM}_raw.png")),
            "geometry": attempt(lambda: load_geometry(geo)),
            "override": attempt(lambda: read_png_ping(b + "/{STEM}_raw.png", geometry=geo)),
            "detect": attempt(lambda: detect_format(geo)),
            "cli_info": cli(["info", geo]),
            "cli_image": cli(["info", a + "/{STEM}_raw.png"]),
        }}))
        """
    )
    for key in ("image", "image_dir", "sidecar", "geometry", "override", "detect"):
        kind, msg = out[key]
        assert kind == "DataFormatError" and "character device" in msg, (key, out[key])
    for key in ("cli_info", "cli_image"):
        rc, lines = out[key]
        assert rc == 1 and len(lines) == 1, (key, lines)
        assert lines[0].startswith("sonarmap: error:") and "character device" in lines[0], (key, lines)


def test_directories_still_allowed(tmp_path: Path, didson_dir: Path) -> None:
    assert detect_format(didson_dir / "test") == "pngjson"
    assert expand_inputs(didson_dir / "test") == [didson_dir / "test"]
    assert len(expand_inputs(str(didson_dir / "test" / "*_raw.png"))) == 10


# ---------------------------------------------------------------------- single beam, constructor
def test_single_beam_geometry_round_trips(tmp_path: Path) -> None:
    g = SonarGeometry(azimuth_rad=[0.1], range_m=[1.0, 1.5, 2.0], fov_rad=0.02, name="one")
    save_geometry(g, tmp_path / "one.json")
    back = load_geometry(tmp_path / "one.json")
    assert back == g and back.fov_rad == 0.02 and back.shape == (3, 1)
    # without a stated width a nominal beam width is assumed (never an fov of 0), and it round-trips
    with pytest.warns(GeometryWarning, match="single beam"):
        w = SonarGeometry.from_window(min_range_m=1.0, max_range_m=3.0, n_bins=4, azimuth_rad=[0.0])
    assert w.fov_rad == SINGLE_BEAM_WIDTH_RAD > 0
    ping = Ping(np.linspace(0, 1, 4, dtype=np.float32)[:, None], w, time_ns=1_000_000_000)
    out = write_png_ping(ping, tmp_path)
    assert json.loads((tmp_path / "1000000.json").read_text())["fov"] > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back_ping = read_png_ping(out)
    assert back_ping.geometry == w and back_ping.shape == (4, 1)
    np.testing.assert_allclose(back_ping.image, ping.image, atol=0.5 / 255)
    # a single beam from num_beams + fov (no table) works as well
    d = {"num_beams": 1, "fov": 0.01, "num_bins": 3, "min_range": 1.0, "max_range": 2.0}
    (tmp_path / "nb1.json").write_text(json.dumps(d))
    with pytest.warns(GeometryWarning, match="uniform"):
        u = load_geometry(tmp_path / "nb1.json")
    assert u.azimuth_rad.tolist() == [0.0] and u.fov_rad == 0.01


def test_geometry_file_with_fov_zero_is_a_clean_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "zero_fov.json"
    path.write_text(json.dumps({"azimuths": [0.0], "fov": 0.0, "num_bins": 3, "min_range": 1.0,
                                "max_range": 2.0}))
    with pytest.raises(GeometryError, match=r"zero_fov\.json: field 'fov' must be in \(0, 2 pi\]"):
        load_geometry(path)
    _assert_one_clean_cli_error(capsys, ["info", str(path)], "zero_fov.json", "fov")


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"n_bins": math.nan}, "num_bins must be an integer, got nan"),
        ({"n_bins": math.inf}, "num_bins must be an integer, got inf"),
        ({"n_bins": 1e308}, "num_bins must be between 1 and 65536"),
        ({"n_bins": 0}, "num_bins must be between 1 and 65536, got 0"),
        ({"n_bins": True}, "num_bins must be an integer, got True"),
        ({"n_bins": 2.5}, "num_bins must be an integer, got 2.5"),
        ({"n_bins": MAX_BINS + 1}, "num_bins must be between"),
        ({"n_beams": 0}, "num_beams must be between 1 and 4096, got 0"),
        ({"n_beams": MAX_BEAMS + 1}, "num_beams must be between"),
        ({"n_beams": 0.5}, "num_beams must be an integer"),
        ({"fov_rad": math.nan}, "fov must be finite"),
        ({"fov_rad": 7.0}, r"fov must be in \(0, 2 pi\]"),
        ({"min_range_m": math.nan}, "min_range must be finite"),
        ({"max_range_m": math.inf}, "max_range must be finite"),
        ({"max_range_m": 1e5}, "max_range: must be at most 25000 m"),
        ({"min_range_m": -1.0}, "min_range: must be >= 0"),
        ({"min_range_m": "1"}, "min_range must be a number, got '1'"),
        ({"noise": True}, "noise must be a number, got True"),
        ({"noise": math.nan}, "noise must be finite"),
        ({"rx_gain_db": 10**400}, "rx_gain_db must be a finite number"),
    ],
)
def test_constructor_refuses_nan_inf_and_absurd_counts(kwargs: dict[str, Any], message: str) -> None:
    kw: dict[str, Any] = {"min_range_m": 1.0, "max_range_m": 2.0, "n_bins": 10, "n_beams": 8, "fov_rad": 0.5}
    kw.update(kwargs)
    with pytest.raises(GeometryError, match=message):
        SonarGeometry.from_window(**kw)


def test_constructor_refuses_bad_arrays_and_windows() -> None:
    r = [1.0, 2.0]
    for kw, message in [
        ({"azimuth_rad": np.linspace(-1, 1, MAX_BEAMS + 1)}, "4097 entries, more than the 4096"),
        ({"range_m": np.linspace(1, 2, MAX_BINS + 1)}, "65537 entries, more than the 65536"),
        ({"range_m": [1.0, 3e4]}, "ranges must be at most 25000 m"),
        ({"azimuth_rad": [True, False]}, "not a numeric array"),
        ({"azimuth_rad": ["0.1"]}, "not a numeric array"),
        ({"azimuth_rad": [10**400]}, "not a numeric array"),
        ({"psf": [1e308, 1e308]}, "psf: sum overflows"),
        ({"fov_rad": "wide"}, "fov_rad must be a number"),
        ({"fov_rad": 0.0}, r"fov_rad: must be in \(0, 2 pi\]"),
        ({"window": (1.0,)}, "window: must be a"),
        ({"window": (2.0, 1.0)}, "window: need 0 <= min_range < max_range"),
        ({"window": (math.nan, 1.0)}, "window min_range must be finite"),
    ]:
        args: dict[str, Any] = {"azimuth_rad": [-0.1, 0.1], "range_m": r, **kw}
        with pytest.raises(GeometryError, match=message):
            SonarGeometry(**args)
    with pytest.raises(GeometryError, match="num_beams must be between"):
        uniform_azimuths(0, 0.5)
    with pytest.raises(GeometryError, match="expected a SonarGeometry, preset name or JSON path"):
        as_geometry(5)  # type: ignore[arg-type]
    assert SonarGeometry(azimuth_rad=[-0.1, 0.1], range_m=r, fov_rad=2 * math.pi).fov_rad == 2 * math.pi


# ---------------------------------------------------------------------- the CLI: one clean line each
def _cli_reproducers(tmp_path: Path, didson_dir: Path) -> list[tuple[str, Path]]:
    side, png = _real_ping(didson_dir)
    cases: list[tuple[str, Path]] = []

    def ping(label: str, sidecar: dict[str, Any] | str | None, image: bytes = png) -> None:
        cases.append((label, _write_ping(tmp_path / label, image, sidecar)))

    for label, change in [("num_beams_0", {"num_beams": 0}), ("num_beams_false", {"num_beams": False}),
                          ("num_beams_half", {"num_beams": 0.5}), ("azimuths_5", {"azimuths": 5}),
                          ("num_bins_nan", {"num_bins": math.nan}), ("num_bins_inf", {"num_bins": math.inf}),
                          ("num_bins_1e308", {"num_bins": 1e308})]:
        ping(label, {**side, **change})
    ping("deep", "[" * 100000)
    ping("bigint", json.dumps({**side, "num_bins": 7}).replace('"num_bins": 7', '"num_bins": ' + "9" * 5000))
    ping("bomb", side, _header_only_png(30000, 30000))
    ping("truncated", side, png[: len(png) // 2])
    geo = tmp_path / "deep_geometry.json"
    geo.write_text("[" * 100000)
    cases.append(("deep_geometry", geo))
    cases.append(("mb2250", didson_dir.parent / "mb2250" / "mb2250.json"))
    return cases


def test_cli_prints_one_error_line_for_every_reproducer(
    tmp_path: Path, didson_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for label, path in _cli_reproducers(tmp_path, didson_dir):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeometryWarning)
            line = _assert_one_clean_cli_error(capsys, ["info", str(path)], path.stem.removesuffix("_raw"))
        assert len(line) < 400, (label, line)


# ---------------------------------------------------------------------- seeded mini-fuzz
_EXTREMES: list[Any] = [
    0, -1, 1, 0.5, -0.0, 1e-320, 1e308, -1e308, math.nan, math.inf, -math.inf, True, False, None,
    "x", "", "NaN", [], {}, [[1.0]], {"a": 1}, 1e9, 4097, 65537, 2**63, 10**400, 96, 512,
]
_HUGE_INT_TEXT = "9" * 5000
_JUNK_DOCS: list[bytes] = [
    b"[" * 100000, b'{"a":' * 50000, b"null", b"[]", b'"text"', b"1e999", b"NaN", b"",
    b"\xff\xfe\x00garbage", b"{" + b" " * 1000, b'{"num_bins": ' + _HUGE_INT_TEXT.encode() + b"}",
    b"\xef\xbb\xbf{}", json.dumps({"x": 1}).encode("utf-16"),
]


def _mutate_json(rng: np.random.Generator, base: dict[str, Any], azimuths: list[float]) -> bytes:
    """One random sidecar: field deletions, type swaps, extreme values, raw-text pathologies."""
    kind = rng.integers(0, 10)
    if kind == 0:
        return _JUNK_DOCS[rng.integers(len(_JUNK_DOCS))]
    d = json.loads(json.dumps(base))
    if rng.random() < 0.3:
        d["azimuths"] = list(azimuths)
    if rng.random() < 0.15:
        d["ranges"] = (2.25 + np.arange(512) * 9.0 / 512).tolist()
    raw_field: str | None = None
    for _ in range(int(rng.integers(1, 4))):
        keys = sorted(d) + ["name", "frequency", "sound_speed", "intensity_scale_absent"]
        key = keys[rng.integers(len(keys))]
        op = rng.integers(0, 6)
        if op == 0 and key in d:
            del d[key]
        elif op == 1:
            d[key] = _EXTREMES[rng.integers(len(_EXTREMES))]
        elif op == 2 and isinstance(d.get(key), list) and d[key]:
            i = int(rng.integers(len(d[key])))
            d[key][i] = _EXTREMES[rng.integers(len(_EXTREMES))]
        elif op == 3 and isinstance(d.get(key), list):
            d[key] = d[key][::-1] if rng.random() < 0.5 else d[key][: int(rng.integers(0, len(d[key]) + 1))]
        elif op == 4:
            d[key] = [d.get(key, 1.0)] * int(rng.choice([0, 1, 95, 96, 97]))
        else:
            raw_field = key
    text = json.dumps(d)
    if raw_field is not None:  # text-level: deep nesting or an oversized integer in one field
        d[raw_field] = "@@RAW@@"
        text = json.dumps(d)
        depth = int(rng.choice([50, 100000]))
        raw = _HUGE_INT_TEXT if rng.random() < 0.5 else "[" * depth + "]" * depth
        text = text.replace('"@@RAW@@"', raw)
    data = text.encode()
    if kind == 1:  # truncated text
        data = data[: int(rng.integers(0, len(data)))]
    return data


def _mutate_image(rng: np.random.Generator, png: bytes, bmp: bytes) -> tuple[bytes, str]:
    """One random image: truncation, bit flips in header or pixel data, rewritten headers."""
    if rng.random() < 0.25:
        data = bytearray(bmp)
        suffix, header_end = "_raw.bmp", 54
    else:
        data = bytearray(png)
        suffix, header_end = "_raw.png", 33
    op = rng.integers(0, 5)
    if op == 0:
        data = data[: int(rng.integers(0, len(data)))]
    elif op in (1, 2):
        lo, hi = (0, header_end) if op == 1 else (header_end, len(data))
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(lo, hi))
            data[i] ^= 1 << int(rng.integers(8))
    elif op == 3 and suffix == "_raw.png":
        dims = [0, 1, 95, 96, 97, 512, 30000, 2**31 - 1]
        data = bytearray(_with_ihdr(
            bytes(data), int(rng.choice(dims)), int(rng.choice(dims)),
            bit_depth=int(rng.choice([1, 2, 4, 8, 16, 3, 0])), colour=int(rng.choice([0, 2, 3, 4, 6, 7])),
            interlace=int(rng.choice([0, 1, 2])),
        ))
    elif op == 3:
        fields = [(18, "<i"), (22, "<i"), (28, "<H"), (30, "<I"), (46, "<I")]
        off, fmt = fields[int(rng.integers(len(fields)))]
        size = struct.calcsize(fmt)
        value = int(rng.choice([0, 1, 96, 512, 40000, 2**15, 2**31 - 1, -(2**31), -512]))
        data[off:off + size] = struct.pack(fmt, value % (2 ** (8 * size)) if fmt[-1] in "HI" else value)
    # op == 4: unchanged image
    return bytes(data), suffix


def _fuzz_case(rng: np.random.Generator, base: dict[str, Any], azimuths: list[float], png: bytes,
               bmp: bytes) -> tuple[bytes, bytes, str]:
    roll = rng.random()
    if roll < 0.6:  # mutate the sidecar only
        return _mutate_json(rng, base, azimuths), png, "_raw.png"
    if roll < 0.9:  # mutate the image only
        image, suffix = _mutate_image(rng, png, bmp)
        return json.dumps(base).encode(), image, suffix
    image, suffix = _mutate_image(rng, png, bmp)  # both
    return _mutate_json(rng, base, azimuths), image, suffix


def _classify(image_path: Path) -> str:
    """``"ok"``, the SonarmapError subclass name, or ``"ESCAPED ..."`` / ``"BAD PING ..."``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeometryWarning)
            ping = read_png_ping(image_path)
    except SonarmapError as exc:
        msg = str(exc)
        if "\n" in msg or len(msg) > 500:
            return f"BAD MESSAGE {type(exc).__name__}: {msg[:200]!r}"
        return type(exc).__name__
    except Exception as exc:  # noqa: BLE001 - exactly what the fuzz looks for
        return f"ESCAPED {type(exc).__name__}: {str(exc)[:200]}"
    img = ping.image
    if not (img.dtype == np.float32 and img.shape == ping.geometry.shape and np.isfinite(img).all()
            and (img.size == 0 or (img.min() >= 0.0 and img.max() <= 1.0))):
        return f"BAD PING dtype={img.dtype} shape={img.shape} geometry={ping.geometry.shape}"
    return "ok"


def run_mini_fuzz(workdir: Path, didson_dir: Path, n_cases: int = 200, seed: int = 20240607) -> Counter[str]:
    """Outcome counts of ``n_cases`` seeded mutations of a real DIDSON sidecar and PNG."""
    base, png = _real_ping(didson_dir)
    azimuths = json.loads((didson_dir / "didson.json").read_text())["azimuths"]
    bmp = _bmp_bytes(png)
    rng = np.random.default_rng(seed)
    outcomes: Counter[str] = Counter()
    for i in range(n_cases):
        sidecar, image, suffix = _fuzz_case(rng, base, azimuths, png, bmp)
        img = _write_ping(workdir / f"case{i:03d}", image, sidecar, stem=str(1468966347000000 + i), suffix=suffix)
        outcomes[_classify(img)] += 1
    return outcomes


def test_mini_fuzz_reads_a_valid_ping_or_raises_a_sonarmap_error(tmp_path: Path, didson_dir: Path) -> None:
    with deadline(60.0), _memory_cap():
        outcomes = run_mini_fuzz(tmp_path, didson_dir)
    bad = {k: v for k, v in outcomes.items() if k.startswith(("ESCAPED", "BAD"))}
    assert not bad, bad
    assert sum(outcomes.values()) == 200
    # the fuzz exercises every path: valid pings, field errors and file-format errors
    assert outcomes["ok"] >= 10 and outcomes["GeometryError"] >= 30 and outcomes["DataFormatError"] >= 30, outcomes


def test_real_pings_and_presets_still_read(didson_dir: Path, data_dir: Path) -> None:
    pings = list(read_pings(didson_dir / "test"))
    assert len(pings) == 10 and all(p.shape == (512, 96) for p in pings)
    assert load_geometry(didson_dir / "didson.json").n_beams == 96
    with pytest.raises(DataFormatError, match="line 3 column 3"):
        load_geometry(data_dir / "mb2250" / "mb2250.json")
    bmp = read_png_ping(didson_dir / "extra" / "frame_2014.bmp", geometry="didson-hf")
    assert bmp.shape == (512, 96)


def test_copy_of_real_ping_reads_identically(tmp_path: Path, didson_dir: Path) -> None:
    src = didson_dir / "test" / f"{STEM}_raw.png"
    shutil.copy(src, tmp_path)
    shutil.copy(didson_dir / "test" / f"{STEM}.json", tmp_path)
    a, b = read_png_ping(src), read_png_ping(tmp_path / src.name)
    np.testing.assert_array_equal(a.image, b.image)
    assert a.geometry == b.geometry
