"""docs/walkthrough.md: the numbers it gives are the ones the commands produce on the real files."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest

from sonarmap.cli import main

WALKTHROUGH = Path(__file__).resolve().parents[1] / "docs" / "walkthrough.md"


def _doc() -> str:
    return " ".join(WALKTHROUGH.read_text(encoding="utf-8").split())


def _returns_m(path: Path) -> list[float]:
    with open(path, newline="") as fh:
        return [float(r["range_m"]) for r in csv.DictReader(fh) if r["range_m"]]


def test_aris_ranges_are_where_the_walkthrough_says(data_dir: Path, tmp_path: Path) -> None:
    """The walkthrough's counts of the ARIS returns, on the target and behind it, are the
    commands' (before, it put all of them on 'the slanted target at about 15.4-17.3 m', where
    some were at 20.3-22.1 m)."""
    m = re.search(r"`ranges` gives (\d+) returns in (\d+) rows \((\d+) without the calibration\), 0 pings "
                  r"flagged: (\d+) of them on the slanted target at about ([\d.]+)-([\d.]+) m, the other (\d+) "
                  r"on weaker echoes at ([\d.]+)-([\d.]+) m", _doc())
    assert m, "the ARIS ranges sentence of docs/walkthrough.md changed"
    n_ret, n_rows, n_plain, n_near, lo, hi, n_far, far_lo, far_hi = m.groups()
    aris = str(data_dir / "aris" / "sample.aris")
    cal, with_cal, plain = tmp_path / "aris.json", tmp_path / "aris.csv", tmp_path / "plain.csv"
    assert main(["calibrate", aris, "-o", str(cal), "-q"]) == 0
    assert main(["ranges", aris, "--calibration", str(cal), "-o", str(with_cal), "-q"]) == 0
    assert main(["ranges", aris, "-o", str(plain), "-q"]) == 0
    r = _returns_m(with_cal)
    assert len(r) == int(n_ret) and len(with_cal.read_text().splitlines()) - 1 == int(n_rows)
    assert len(_returns_m(plain)) == int(n_plain)
    near, far = [v for v in r if v < 19.0], [v for v in r if v >= 19.0]
    assert len(near) == int(n_near) and len(far) == int(n_far)
    assert f"{min(near):.1f}-{max(near):.1f}" == f"{lo}-{hi}"
    assert f"{min(far):.1f}-{max(far):.1f}" == f"{far_lo}-{far_hi}"


def test_oculus_occupancy_cells_are_what_the_walkthrough_says(data_dir: Path, tmp_path: Path) -> None:
    """The walkthrough states how many occupied cells the command writes."""
    m = re.search(r"`map --grid 0\.01 --dims 2` writes the (\d+) occupied", _doc())
    assert m, "the Oculus map sentence of docs/walkthrough.md changed"
    raw = str(data_dir / "oculus" / "three_pings_8bit.raw")
    cal, cells = tmp_path / "oculus.json", tmp_path / "oculus-occ.csv"
    assert main(["calibrate", raw, "-o", str(cal), "-q"]) == 0
    assert main(["map", raw, "--static", "--calibration", str(cal), "--grid", "0.01", "--dims", "2",
                 "-o", str(cells), "-q"]) == 0
    assert len(cells.read_text().splitlines()) - 1 == int(m.group(1))
