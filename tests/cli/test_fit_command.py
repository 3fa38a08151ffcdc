"""``sonarmap fit``: what --recipe does to images that are normalised."""

from __future__ import annotations

from pathlib import Path

import pytest

from sonarmap.cli import main


def test_a_recipe_that_is_not_applied_is_said_once(data_dir: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap fit sample.aris --recipe paper-table1' wrote the same CSV as without
    --recipe and said nothing (ARIS images are normalised, which takes precedence). Now one
    warning line says so and how to fit the recipe's image; --no-normalise applies the recipe."""
    aris = str(data_dir / "aris" / "sample.aris")
    plain, with_recipe, raw = (tmp_path / n for n in ("plain.csv", "recipe.csv", "raw.csv"))
    assert main(["fit", aris, "-o", str(plain), "-q"]) == 0
    capsys.readouterr()
    assert main(["fit", aris, "-o", str(with_recipe), "-q", "--recipe", "paper-table1"]) == 0
    err = capsys.readouterr().err
    assert with_recipe.read_text() == plain.read_text()
    warning = [ln for ln in err.splitlines() if ln.startswith("sonarmap: warning:")]
    assert len(warning) == 1 and "--recipe paper-table1 was not applied to 6 of 6 pings" in warning[0]
    assert "--no-normalise" in warning[0]
    assert main(["fit", aris, "-o", str(raw), "-q", "--recipe", "paper-table1", "--no-normalise"]) == 0
    assert "warning" not in capsys.readouterr().err and raw.read_text() != plain.read_text()
