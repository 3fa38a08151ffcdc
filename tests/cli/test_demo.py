"""`sonarmap demo`: simulate a hull survey, process it, build the map and the report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from browser import page_errors, screenshot


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    out = tmp_path_factory.mktemp("demo") / "demo"
    r = subprocess.run([sys.executable, "-m", "sonarmap", "demo", "-o", str(out), "--pings", "16"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return out, r


@pytest.mark.slow
def test_demo_writes_and_lists_every_output(demo: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    out, r = demo
    for name in ("pings", "poses.csv", "survey.zarr", "map.ply", "report.html"):
        assert (out / name).exists(), name
        assert str(out / name) in r.stdout, f"{name} location not printed"
    assert len(list((out / "pings").glob("*_raw.png"))) == 16
    from sonarmap.survey import open_products, survey_status

    assert survey_status(out / "survey.zarr")["complete"]
    ds = open_products(out / "survey.zarr")
    assert ds.sizes["ping_time"] == 16
    # The hull is seen: most pings have returns, and they were registered into map points.
    assert np.isfinite(ds["range"].values).any(axis=1).mean() > 0.5
    assert ds.sizes["point"] > 16 * 10
    from sonarmap.mapping import read_point_cloud

    assert len(read_point_cloud(out / "map.ply")) == ds.sizes["point"]
    assert "map accuracy" in r.stdout


@pytest.mark.slow
def test_demo_report_has_map_and_renders(demo: tuple[Path, subprocess.CompletedProcess[str]], tmp_path: Path) -> None:
    out, _ = demo
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "Map preview" in html and "Example pings" in html
    log = screenshot(out / "report.html", tmp_path / "demo.png")
    assert page_errors(log) == []


@pytest.mark.slow
def test_demo_refuses_to_overwrite(demo: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    out, _ = demo
    r = subprocess.run([sys.executable, "-m", "sonarmap", "demo", "-o", str(out), "--pings", "4"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "--overwrite" in r.stderr
    assert len(list((out / "pings").glob("*_raw.png"))) == 16
