"""``--start-time`` / ``--ping-rate``: the times of recordings without a clock (Oculus captures)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import typer

from sonarmap.cli import main
from sonarmap.cli._common import clock_options

START_NS = 1_714_558_830_500_000_000  # 2024-05-01T10:20:30.5Z


@pytest.mark.parametrize("text", ["2024-05-01T10:20:30.5Z", "2024-05-01T10:20:30.500000000",
                                  "2024-05-01T12:20:30.5+02:00", "2024-05-01T07:50:30.5-0230", str(START_NS)])
def test_start_time_forms(text: str) -> None:
    assert clock_options(text, None) == {"start_time_ns": START_NS}


@pytest.mark.parametrize("text", ["yesterday", "2024", "1714558830", "2024-13-01T00:00:00Z", ""])
def test_bad_start_time_is_a_usage_error(text: str) -> None:
    with pytest.raises(typer.BadParameter, match="start-time|ISO 8601"):
        clock_options(text, None)


@pytest.mark.parametrize("rate", [0.0, -1.0, float("nan"), float("inf"), 2e6])
def test_bad_ping_rate_is_a_usage_error(rate: float) -> None:
    with pytest.raises(typer.BadParameter, match="pings per second"):
        clock_options(None, rate)


def test_ranges_and_convert_take_the_clock(data_dir: Path, tmp_path: Path) -> None:
    cap = data_dir / "oculus" / "three_pings_8bit.raw"
    out = tmp_path / "r.csv"
    assert main(["ranges", str(cap), "-o", str(out), "--start-time", "2024-05-01T10:20:30.5Z",
                 "--ping-rate", "15", "-q"]) == 0
    df = pd.read_csv(out, parse_dates=["time"])
    per_ping = df.groupby("ping")["time_ns"].first().sort_values().tolist()
    assert per_ping == [START_NS + round(i * 1e9 / 15) for i in range(3)]
    assert str(df["time"].iloc[0]) == "2024-05-01 10:20:30.500000+00:00"
    import xarray as xr

    store = tmp_path / "s.zarr"
    assert main(["convert", str(cap), "-o", str(store), "--start-time", str(START_NS), "-q"]) == 0
    times = xr.open_zarr(store).ping_time.values.astype("int64").tolist()
    assert times == [START_NS + i * 100_000_000 for i in range(3)]  # the default 10 Hz


def test_clock_options_on_a_recording_with_a_clock_warn_and_change_nothing(
    data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    aris = data_dir / "aris" / "sample.aris"
    assert main(["ranges", str(aris), "-o", str(tmp_path / "a.csv"), "--start-time", "2024-05-01T10:20:30Z", "-q"]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "has its own ping times; --start-time / --ping-rate ignored" in err
    assert main(["ranges", str(aris), "-o", str(tmp_path / "b.csv"), "-q"]) == 0
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_bad_clock_option_exits_2_before_any_output(data_dir: Path, tmp_path: Path) -> None:
    cap = data_dir / "oculus" / "three_pings_8bit.raw"
    for cmd in (["ranges", str(cap), "-o", str(tmp_path / "x.csv")],
                ["map", str(cap), "--static", "-o", str(tmp_path / "x.csv")],
                ["convert", str(cap), "-o", str(tmp_path / "x.zarr")],
                ["segment", str(cap), "-o", str(tmp_path / "seg")]):
        assert main([*cmd, "--ping-rate", "0"]) == 2, cmd
        assert main([*cmd, "--start-time", "soon"]) == 2, cmd
    assert list(tmp_path.iterdir()) == []
