"""``python -m sonarmap.simulate.compare``: its options are parsed, not read as data paths."""

from __future__ import annotations

import pytest

from sonarmap.simulate.compare import main


def test_help_prints_the_usage_and_exits_0(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--ghosts" in out and "--all" in out


def test_an_unknown_option_is_a_usage_error(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--bogus"])
    assert exc.value.code == 2
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err


def test_ghosts_of_the_diagonal_hull_ping(data_dir, capsys) -> None:
    assert main(["--ghosts", str(data_dir / "didson" / "test" / "1468970074505798_raw.png")]) == 0
    assert capsys.readouterr().out.strip() == "ghost ratios at +-8, +-16, +-24 beams: (0.031, 0.007, 0.005)"
