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


@pytest.mark.parametrize(("crs", "says"), [("EPSG:4326", "is not a projected CRS"),
                                           ("EPSG:99999", "cannot interpret 'EPSG:99999'")])
def test_a_crs_that_cannot_be_used_is_a_usage_error(crs: str, says: str, test_ping_paths: list[Path], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap map X --static --origin 42,-71 --crs EPSG:4326 -o m.ply' exited 1 with
    'crs: EPSG:4326 is not a projected CRS ...' (the library's argument name); now exit 2 naming
    --crs, before anything is read or written."""
    out = tmp_path / "m.ply"
    assert main(["map", str(test_ping_paths[0]), "--static", "--origin", "42,-71", "--crs", crs, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "Invalid value for --crs" in err and says in err and "━" not in err and not out.exists()


def test_an_unknown_output_suffix_names_every_output_the_help_offers(test_ping_paths: list[Path], tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap map X --static -o m.tif' said 'output: cannot infer the point-cloud format
    from suffix '.tif'; use .ply, .las or .csv', leaving out the ROS bags -o takes."""
    assert main(["map", str(test_ping_paths[0]), "--static", "-o", str(tmp_path / "m.tif")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "Invalid value for --output: cannot infer" in err and ".bag or --format bag2 for a ROS bag" in err
