"""``sonarmap calibrate`` and ``sonarmap fit`` end to end."""

from __future__ import annotations

import csv
import json

from sonarmap.cli import main
from sonarmap.geometry import load_geometry


def test_calibrate_round_trip(didson_dir, tmp_path):
    out = tmp_path / "sonar.json"
    assert main(["calibrate", str(didson_dir / "background"), "-o", str(out)]) == 0
    d = json.loads(out.read_text())
    cal = d["calibration"]
    assert abs(cal["pi_B"] - 0.312) <= 0.005
    assert abs(cal["lambda"] / 44.6 - 1) <= 0.03
    g = load_geometry(out)
    assert g.shape == (512, 96) and g.taper is not None


def test_fit_command(test_ping_paths, tmp_path):
    out = tmp_path / "params.csv"
    assert main(["fit", *map(str, test_ping_paths[:2]), "-o", str(out), "-m", "em"]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [r["ping"] for r in rows] == [p.name for p in test_ping_paths[:2]]
    assert set(rows[0]) == {"ping", "family", "weights", "scales", "kld", "flags"}
    assert abs(sum(float(v) for v in rows[0]["weights"].split(";")) - 1) < 1e-6
