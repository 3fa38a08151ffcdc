"""The Reader protocol: every format module detects, counts and reads ranges of pings alike."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from ddf_writer import write_ddf
from kmall_writer import write_kmall

from sonarmap.errors import DataFormatError, InputError
from sonarmap.io import Reader, read_ping, read_pings, reader_for, reader_modules
from sonarmap.io import aris as aris_mod
from sonarmap.store import write_survey
from sonarmap.io.reader import FORMAT_MODULES, check_ping_range
from sonarmap.io.rosbag import write_bag


def _key(ping) -> tuple:
    img = np.ascontiguousarray(ping.image)
    g = ping.geometry
    return (img.dtype.str, img.shape, img.tobytes(), ping.time_ns, ping.source, g.name,
            g.azimuth_rad.tobytes(), g.range_m.tobytes(), repr(sorted(ping.meta.items())))


@pytest.fixture(scope="module")
def recordings(data_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One input per reader: the real recordings, and written DDF / KMALL / bags / store."""
    tmp = tmp_path_factory.mktemp("readers")
    rng = np.random.default_rng(3)
    ddf = tmp / "s.ddf"
    write_ddf(ddf, [rng.integers(0, 256, (64, 48), dtype=np.uint8) for _ in range(5)], version=3)
    kmall = tmp / "s.kmall"
    write_kmall(kmall)
    didson = data_dir / "didson" / "test"
    pings = list(read_pings(didson))[:6]
    bag1, bag2 = tmp / "s.bag", tmp / "s_bag2"
    write_bag(pings, bag1, version=1)
    write_bag(pings, bag2, version=2)
    store = tmp / "s.zarr"
    write_survey(pings, store, chunk_pings=4)
    return {
        "aris": data_dir / "aris" / "sample.aris",
        "oculus": data_dir / "oculus" / "three_pings_8bit.raw",
        "kongsberg": data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all",
        "pngjson": didson,
        "ddf": ddf,
        "kmall": kmall,
        "rosbag": bag1,
        "rosbag2": bag2,
        "zarr": store,
    }


def test_every_format_module_is_a_reader() -> None:
    mods = reader_modules()
    assert [m.__name__.rsplit(".", 1)[-1] for m in mods] == list(FORMAT_MODULES)
    for mod in mods:
        assert isinstance(mod, Reader), mod.__name__
        assert reader_for(mod.FORMAT) is mod
    assert reader_for("zarrstore").FORMAT == "zarr"


@pytest.mark.parametrize("name", ["aris", "oculus", "kongsberg", "pngjson", "ddf", "kmall", "rosbag", "rosbag2", "zarr"])
def test_ranges_are_slices_of_the_whole(recordings: dict[str, Path], name: str) -> None:
    path = recordings[name]
    reader = reader_for(path)
    assert reader.FORMAT == {"rosbag2": "rosbag"}.get(name, name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # truncated last Kongsberg ping, guessed bag conventions
        whole = [_key(p) for p in reader.iter_pings(path)]
        assert len(whole) == reader.count_pings(path) >= 3
        n = len(whole)
        for start, stop in [(0, None), (1, None), (1, 3), (n - 1, None), (n - 1, n + 5), (2, 2), (3, 1), (n, None)]:
            got = [_key(p) for p in reader.iter_pings(path, start=start, stop=stop)]
            assert got == whole[start:stop], (start, stop)
        assert _key(read_ping(path, index=n - 1)) == whole[-1]
        with pytest.raises(DataFormatError, match=f"no ping with index {n}"):
            read_ping(path, index=n)


def test_pings_before_start_are_not_decoded(recordings: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    decoded: list[int] = []
    original = aris_mod.ArisFile._ping

    def counting(self, i: int):
        decoded.append(i)
        return original(self, i)

    monkeypatch.setattr(aris_mod.ArisFile, "_ping", counting)
    got = list(aris_mod.iter_pings(recordings["aris"], start=4, stop=5))
    assert len(got) == 1 and decoded == [4]
    decoded.clear()
    read_ping(recordings["aris"], index=5)
    assert decoded == [5]


@pytest.mark.parametrize("start,stop", [(-1, None), (0, -2), (1.5, None), (True, None), ("1", None)])
def test_bad_ranges_are_refused(recordings: dict[str, Path], start, stop) -> None:
    with pytest.raises(InputError, match="start|stop"):
        check_ping_range(start, stop)
    for name in ("aris", "pngjson", "zarr", "rosbag"):
        with pytest.raises(InputError, match="start|stop"):
            list(reader_for(recordings[name]).iter_pings(recordings[name], start=start, stop=stop))


def test_reader_for_unknown_inputs(tmp_path: Path) -> None:
    junk = tmp_path / "x.bin"
    junk.write_bytes(b"\x00" * 4096)
    with pytest.raises(DataFormatError):
        reader_for(junk)
    with pytest.raises(DataFormatError):
        reader_for(tmp_path / "missing.aris")
