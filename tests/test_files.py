"""Bounded reads of untrusted regular files (sonarmap._files)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sonarmap._files import read_bytes_bounded
from sonarmap.errors import DataFormatError


def test_read_bytes_bounded_reads_the_whole_file_up_to_the_bound(tmp_path: Path) -> None:
    p = tmp_path / "s.json"
    p.write_bytes(b"x" * 100)
    assert read_bytes_bounded(p, 100) == b"x" * 100
    assert read_bytes_bounded(tmp_path / "s.json", 1 << 24) == b"x" * 100
    p.write_bytes(b"")
    assert read_bytes_bounded(p, 10) == b""
    p.write_bytes(b"y" * 101)
    with pytest.raises(DataFormatError, match="101 bytes, more than the 100 allowed"):
        read_bytes_bounded(p, 100)


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs /proc")
def test_read_bytes_bounded_reads_past_a_size_of_zero() -> None:
    # a regular file whose stat size (0) is not its length, as a file growing while read
    data = read_bytes_bounded("/proc/self/status", 1 << 20)
    assert data.startswith(b"Name:") and len(data) > 100
    with pytest.raises(DataFormatError, match="more than the 10 bytes allowed"):
        read_bytes_bounded("/proc/self/status", 10)
