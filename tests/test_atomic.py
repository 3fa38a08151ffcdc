"""Outputs that are directories (stores, bags) are built beside their target and moved onto it with
renames only; a replaced or removed output is renamed aside first; leftovers of killed writers go."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sonarmap._atomic import remove_output, remove_stale_dirs, replace_output, temp_dir_beside


def _tree(d: Path) -> dict[str, str]:
    return {str(p.relative_to(d)): p.read_text() for p in sorted(d.rglob("*")) if p.is_file()}


def test_replace_output_replaces_a_directory_or_file_and_leaves_nothing_beside(tmp_path: Path) -> None:
    target = tmp_path / "s.zarr"
    for old in ("dir", "file", None):
        if old == "dir":
            (target / "a").mkdir(parents=True)
            (target / "a" / "x").write_text("old")
        elif old == "file":
            target.write_text("old file")
        new = temp_dir_beside(target)
        assert new.parent == tmp_path and new.name.startswith(".s.zarr.") and new.name.endswith(".tmp")
        (new / "b").write_text(f"new over {old}")
        replace_output(new, target)
        assert _tree(target) == {"b": f"new over {old}"}
        assert sorted(os.listdir(tmp_path)) == ["s.zarr"]
        remove_output(target)
        assert os.listdir(tmp_path) == []
    remove_output(target)  # nothing there: nothing to do


def test_a_failed_replace_keeps_the_old_output(tmp_path: Path) -> None:
    target = tmp_path / "s.zarr"
    target.mkdir()
    (target / "x").write_text("old")
    with pytest.raises(OSError):
        replace_output(tmp_path / "missing", target)
    assert _tree(target) == {"x": "old"}
    assert sorted(os.listdir(tmp_path)) == ["s.zarr"]


def test_stale_directories_of_killed_writers_are_removed(tmp_path: Path) -> None:
    target = tmp_path / "s.zarr"
    stale = [".s.zarr.abcd_123.tmp", ".s.zarr.x1y2z3w4.old", ".s.zarr.old-4242"]
    kept = [".s.zarr.lock", ".other.zarr.abcd_123.tmp", ".s.zarr.toolong99.tmp", "s.zarr"]
    for name in stale + kept:
        (tmp_path / name).mkdir()
    assert sorted(p.name for p in remove_stale_dirs(target)) == sorted(stale)
    assert sorted(os.listdir(tmp_path)) == sorted(kept)


def test_an_output_that_is_a_directory_is_refused_before_writing(tmp_path: Path) -> None:
    """Before: atomic_path wrote the whole temporary file and then failed to replace the
    directory ('cannot write: Is a directory'), after a command had done all its work."""
    from sonarmap._atomic import atomic_path
    from sonarmap.errors import DataFormatError

    with pytest.raises(DataFormatError, match="is a directory; give a file name"):
        with atomic_path(tmp_path):
            pytest.fail("the block must not run")
    assert list(tmp_path.iterdir()) == []


def test_an_output_directory_in_the_way_of_a_file_is_named(tmp_path: Path) -> None:
    """Before: 'sonarmap segment X -o afile' said '[Errno 17] File exists: 'afile'', demo
    '[Errno 20] Not a directory: 'afile/pings''."""
    from sonarmap._atomic import make_output_dir
    from sonarmap.errors import DataFormatError

    (tmp_path / "afile").write_text("x")
    for target in (tmp_path / "afile", tmp_path / "afile" / "pings" / "deeper"):
        with pytest.raises(DataFormatError, match=r"afile: exists and is not a directory; give a directory$"):
            make_output_dir(target)
    assert make_output_dir(tmp_path / "new" / "dir").is_dir()
