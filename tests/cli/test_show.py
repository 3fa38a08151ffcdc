"""``sonarmap show``: option values checked before anything is drawn."""

from __future__ import annotations

from pathlib import Path

import pytest

from sonarmap.cli import main


@pytest.mark.parametrize(("option", "value", "says"), [
    ("--resolution", "0", "positive"),
    ("--resolution", "-1", "positive"),
    ("--resolution", "nan", "positive"),
    ("--resolution", "1e-9", "at least"),
    ("--vmax", "nan", "finite"),
    ("--vmax", "inf", "finite"),
])
def test_bad_resolution_or_vmax_is_a_usage_error(option: str, value: str, says: str, data_dir: Path,
                                                 tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Before: --resolution 0 / -1 exited 1 naming the library's 'resolution_m', 1e-9 ended in an
    internal MemoryError (150 GiB), --vmax nan drew a figure. Now each is a usage error (exit 2)
    naming the option, and nothing is written."""
    out = tmp_path / "fan.png"
    code = main(["show", str(data_dir / "aris" / "sample.aris"), "-o", str(out), option, value])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"Invalid value for {option}" in err and says in err and "MemoryError" not in err
    assert not out.exists()


def test_labels_of_a_recording_are_a_usage_error(data_dir: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap show sample.aris --image labels -o x.png' drew the raw ping and said
    nothing; a recording has no stored labels (--image is for product stores)."""
    out = tmp_path / "x.png"
    assert main(["show", str(data_dir / "aris" / "sample.aris"), "--image", "labels", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "Invalid value for --image" in err and "product store" in err and not out.exists()
