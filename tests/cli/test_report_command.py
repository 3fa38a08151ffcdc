"""``sonarmap report``: what it says when STORE is not a product store."""

from __future__ import annotations

from pathlib import Path

import pytest

from sonarmap.cli import main


def test_a_raw_ping_store_is_named_as_one(test_ping_paths: list[Path], tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Before: the store of 'sonarmap convert' (which the docs call a survey store) and a path
    that does not exist both gave 'not a sonarmap survey store'. Now the first says to process it
    first, the second that it does not exist; one line, exit 1."""
    from sonarmap.io import read_pings
    from sonarmap.store import write_survey

    raw = tmp_path / "raw.zarr"
    write_survey(read_pings([str(p) for p in test_ping_paths[:2]]), raw)
    assert main(["report", str(raw), "-o", str(tmp_path / "r.html")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "raw pings (sonarmap convert)" in err
    assert f"sonarmap process {raw} -o" in err
    assert main(["report", str(tmp_path / "missing.zarr"), "-o", str(tmp_path / "r.html")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.zarr: no such file or directory" in err
    assert not (tmp_path / "r.html").exists()
