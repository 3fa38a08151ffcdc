"""One entry point: read_pings detects formats by content (not extension) and yields lazily."""

from __future__ import annotations

import re
import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from ddf_writer import write_ddf

from sonarmap.errors import DataFormatError
from sonarmap.io import detect_format, format_module, read_pings
from sonarmap.store import write_survey
from sonarmap.io.rosbag import write_bag


@pytest.mark.slow  # over a second in the fast subset
def test_detection_by_content_not_extension(data_dir: Path, tmp_path: Path) -> None:
    # copies with misleading names (temp files, never in the repo)
    a = tmp_path / "recording.dat"
    shutil.copy(data_dir / "aris" / "sample.aris", a)
    o = tmp_path / "ping.aris"
    shutil.copy(data_dir / "oculus" / "one_ping_8bit.raw", o)
    d = tmp_path / "x.bin"
    write_ddf(d, [np.zeros((512, 96), np.uint8)])
    b = tmp_path / "bag.raw"
    write_bag([next(read_pings(o))], b, version=1)
    b2 = tmp_path / "ros2"
    write_bag([next(read_pings(o))], b2, version=2)
    z = tmp_path / "survey"
    write_survey(read_pings(o), z)
    assert [detect_format(p) for p in (a, o, d, b, b2, z)] == ["aris", "oculus", "ddf", "rosbag", "rosbag", "zarr"]
    assert [len(list(read_pings(p))) for p in (a, o, d, b, b2, z)] == [6, 1, 1, 1, 1, 1]
    for name in ("aris", "oculus", "ddf", "rosbag", "zarr", "pngjson"):
        mod = format_module(name)
        assert all(hasattr(mod, f) for f in ("sniff", "iter_pings", "count_pings"))
        if name != "pngjson":
            assert hasattr(mod, "summary")


def test_unknown_content(tmp_path: Path) -> None:
    p = tmp_path / "sample.aris"
    p.write_bytes(b"SOME TEXT that starts like an Oculus message id")
    with pytest.raises(DataFormatError, match="unrecognised file format"):
        list(read_pings(p))


def test_an_empty_file_is_called_empty(tmp_path: Path) -> None:
    """A 0-byte file (a recording that was never written to) says so, not 'unrecognised format'."""
    p = tmp_path / "sample.aris"
    p.write_bytes(b"")
    with pytest.raises(DataFormatError, match=r"sample\.aris: empty file \(0 bytes\): no pings"):
        list(read_pings(p))


def test_several_inputs_in_order_and_lazy(data_dir: Path) -> None:
    paths = [data_dir / "oculus" / "three_pings_8bit.raw", data_dir / "aris" / "sample.aris"]
    it = read_pings(paths)
    tracemalloc.start()
    first = next(it)  # nothing is read before the first ping is asked for
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert first.meta["format"] == "oculus"
    assert peak < 20e6  # one ping in memory, not the recordings
    rest = list(it)
    assert [p.meta["format"] for p in rest] == ["oculus"] * 2 + ["aris"] * 6


def test_png_folder_still_works(didson_dir: Path) -> None:
    pings = list(read_pings(didson_dir / "test"))
    assert len(pings) == 10 and pings[0].shape == (512, 96)


def test_a_folder_of_recordings_is_read_recording_by_recording(data_dir: Path, tmp_path: Path) -> None:
    """A directory without ping images stands for the recordings in it, in name order; licences,
    READMEs, beam tables and subdirectories are passed over."""
    from sonarmap.io import expand_inputs, total_pings
    from sonarmap.survey.plan import plan_survey

    d = tmp_path / "dives"
    d.mkdir()
    (d / "b_second.aris").symlink_to(data_dir / "aris" / "sample.aris")
    (d / "a_first.raw").symlink_to(data_dir / "oculus" / "three_pings_8bit.raw")
    (d / "LICENSE").write_text("MIT")
    (d / "BeamWidths.h").symlink_to(data_dir / "aris" / "BeamWidths_ARIS3000_128.h")
    (d / "notes").mkdir()
    assert [p.name for p in expand_inputs(d)] == ["a_first.raw", "b_second.aris"]
    assert [p.meta["format"] for p in read_pings(d)] == ["oculus"] * 3 + ["aris"] * 6
    assert total_pings(expand_inputs(d)) == 9
    assert sum(n for _, _, n in plan_survey([d]).files) == 9
    # the shared Kongsberg folder: its .all + .wcd pair is one recording, the README and LICENSE
    # are skipped
    kong = data_dir / "kongsberg"
    n = len(list(read_pings(next(kong.glob("*.all")))))  # 10
    assert len(list(read_pings(kong))) == n
    # given as two files (or a glob), the pair is planned and counted once, as it is read
    pair = [next(kong.glob("*.wcd")), next(kong.glob("*.all"))]
    assert [k for _, _, k in plan_survey([kong]).files] == [n]
    assert [k for _, _, k in plan_survey(pair).files] == [n]
    assert total_pings(expand_inputs(pair)) == n == total_pings(expand_inputs(kong))


def test_a_folder_without_pings_says_where_they_are(didson_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match=r"no pings found.*subdirectories: background/, extra/, test/"):
        list(read_pings(didson_dir))
    (tmp_path / "README.md").write_text("nothing here")
    with pytest.raises(DataFormatError, match=r"no pings found: no PNG/BMP ping images and no recording"):
        list(read_pings(tmp_path))


@pytest.mark.parametrize(("name", "index", "held"), [
    ("oculus/one_ping_8bit.raw", 1, "(it has 1 ping: index 0)"),
    ("aris/sample.aris", 99, "(it has 6 pings: 0-5)"),
    ("didson/test", 10, "(it has 10 pings: 0-9)"),
])
def test_a_missing_index_says_which_indices_there_are(name: str, index: int, held: str, data_dir: Path) -> None:
    """Before: 'sonarmap show one_ping_8bit.raw -i 1 ...' said only 'has no ping with index 1'."""
    from sonarmap.errors import DataFormatError
    from sonarmap.io import read_ping

    with pytest.raises(DataFormatError, match=re.escape(f"has no ping with index {index} {held}")):
        read_ping(data_dir / name, index=index)
