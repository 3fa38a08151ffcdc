"""``sonarmap map``: its summary line names every file it wrote and the CRS of a georeferenced map."""

from __future__ import annotations

from pathlib import Path

import pytest

from sonarmap.cli import main


@pytest.mark.slow
def test_summary_names_the_crs_and_every_output(test_ping_paths: list[Path], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap map ... --origin LAT,LON -o d.las --geotiff depth.tif' printed only
    '1 ping, N returns -> N points in d.las': neither the CRS nor the GeoTIFF it also wrote."""
    las, tif = tmp_path / "d.las", tmp_path / "depth.tif"
    pings = [str(test_ping_paths[4])]
    assert main(["map", *pings, "--static", "--origin", "42.3601,-71.0589", "-o", str(las),
                 "--geotiff", str(tif)]) == 0
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert las.exists() and tif.exists()
    assert line.startswith("1 ping, ") and f"points in {las} (EPSG:32619)" in line
    assert line.endswith(f"; bathymetry GeoTIFF -> {tif}")
