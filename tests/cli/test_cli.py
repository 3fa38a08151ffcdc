"""CLI behaviour: exit codes, one-line errors, info/show on real data."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from sonarmap.cli import main


def test_info_on_real_ping(capsys: pytest.CaptureFixture[str], test_ping_paths: list[Path]) -> None:
    assert main(["info", str(test_ping_paths[0])]) == 0
    out = capsys.readouterr().out
    assert "96" in out and "512" in out
    assert "2.25" in out and "11.25" in out
    assert "-14.7177" in out and "14.0942" in out


def test_info_on_folders_describes_each_recording(capsys: pytest.CaptureFixture[str], data_dir: Path) -> None:
    """A folder of recordings: one entry per recording (it said 'format pngjson' for the Oculus
    folder, summing its files' pings); the Kongsberg .all + .wcd pair is one recording."""
    import json

    assert main(["info", "--json", str(data_dir / "oculus"), str(data_dir / "kongsberg")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert [(Path(x["path"]).name, x["format"], x["pings"]) for x in d] == [
        ("one_ping_8bit.raw", "oculus", 1), ("three_pings_8bit.raw", "oculus", 3),
        ("0077_20221109_123655_Belgica.all", "kongsberg", 10)]
    assert main(["info", str(data_dir / "didson")]) == 1
    assert "pass one of its subdirectories: background/, extra/, test/" in capsys.readouterr().err


def test_info_json_and_presets(capsys: pytest.CaptureFixture[str], didson_dir: Path) -> None:
    import json

    assert main(["info", "--json", str(didson_dir / "didson.json")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["kind"] == "geometry" and d["beams"] == 96 and d["azimuth_table"] == "non-uniform"
    assert d["azimuth_beamwidth_deg"] is None  # the sidecar does not give it
    assert main(["info", "--presets", "--json"]) == 0
    presets = {p["preset"]: p for p in json.loads(capsys.readouterr().out)}
    assert len(presets) == 8
    assert presets["didson-hf"]["azimuth_beamwidth_deg"] == pytest.approx(0.3)  # two-way -3 dB


def test_malformed_json_exits_1_one_line(capsys: pytest.CaptureFixture[str], data_dir: Path) -> None:
    path = data_dir / "mb2250" / "mb2250.json"
    assert main(["info", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "line 3 column 3" in err
    assert "Traceback" not in err


def test_long_lines_are_not_wrapped_or_cut_on_a_pipe(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch, data_dir: Path,
                                                     test_ping_paths: list[Path]) -> None:
    """On a pipe or file rich assumes 80 columns: info's values must not be cut with an ellipsis
    and a one-line summary must stay one line, whatever the length of the paths in them."""
    monkeypatch.delenv("COLUMNS", raising=False)
    link = tmp_path / ("a-long-file-name-" * 6 + ".aris")
    link.symlink_to(data_dir / "aris" / "sample.aris")
    assert main(["info", str(link)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    assert ["path", str(link)] in rows
    csv = tmp_path / ("another-long-directory-name-" * 3) / "ranges.csv"
    assert main(["ranges", str(test_ping_paths[0]), "-o", str(csv)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert any(str(csv) in line and line.endswith("solver=graphcut)") for line in err), err


def test_info_lines_have_no_trailing_blanks(capsys: pytest.CaptureFixture[str], data_dir: Path) -> None:
    """info's table is text for people and scripts: no row is padded with blanks to the widest value."""
    assert main(["info", str(data_dir / "aris" / "sample.aris"), str(data_dir / "didson" / "didson.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) > 40 and [ln for ln in lines if ln != ln.rstrip()] == []


def test_help_paragraphs_are_wrapped_as_paragraphs(capsys: pytest.CaptureFixture[str],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A command's --help description flows as paragraphs: no line is broken in two because the
    docstring's source lines are wider than the terminal (a long line, then a stub of a word or two)."""
    from sonarmap.cli import app

    monkeypatch.setenv("COLUMNS", "80")
    for info in app.registered_commands:
        name = info.name or info.callback.__name__
        assert main([name, "--help"]) == 0
        out = capsys.readouterr().out
        text = out.split("Usage:", 1)[1].split("╭", 1)[0].splitlines()[2:]  # the description
        lines = [line.strip() for line in text]
        for line, after in zip(lines, lines[1:], strict=False):
            assert not (line and after and len(line) < 40), f"sonarmap {name} --help: stub line {line!r}"


def test_usage_error_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["info", "--no-such-option"]) == 2
    assert main(["no-such-command"]) == 2


def test_debug_shows_traceback(data_dir: Path) -> None:
    from sonarmap.errors import DataFormatError

    with pytest.raises(DataFormatError):
        main(["--debug", "info", str(data_dir / "mb2250" / "mb2250.json")])


@pytest.mark.slow
def test_show_writes_figure(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    out = tmp_path / "fan.png"
    assert main(["show", str(test_ping_paths[7]), "-o", str(out), "--polar"]) == 0
    from PIL import Image

    with Image.open(out) as im:
        assert im.size[0] > 400 and im.size[1] > 300


@pytest.mark.slow
def test_console_script_subprocess(test_ping_paths: list[Path]) -> None:
    r = subprocess.run([sys.executable, "-m", "sonarmap", "info", str(test_ping_paths[0])],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([sys.executable, "-m", "sonarmap", "info", "missing.png"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stderr.strip() == "sonarmap: error: missing.png: no such file or directory"


def test_simulate_refuses_a_count_that_would_fill_the_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """--count against the free space (here 1 MB): one error line naming --count, nothing written."""
    import collections
    import shutil

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 10**6, 10**6))
    out = tmp_path / "sim"
    assert main(["simulate", "--count", "40", "-o", str(out), "-q"]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("sonarmap: error: --count 40: the pings would take about "), err
    assert "free on" in err[0] and "ask for at most" in err[0], err
    assert not out.exists()
    monkeypatch.undo()
    assert main(["simulate", "--count", "2", "-o", str(out), "-q"]) == 0
    assert len(list(out.glob("*_raw.png"))) == 2



@pytest.mark.parametrize("cmd", ["ranges", "fit", "segment", "convert", "map", "simulate", "preprocess"])
def test_summaries_of_one_ping_say_ping_not_pings(cmd: str, test_ping_paths: list[Path], tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap ranges' on one ping said '1 pings, 96 rows ...' and '0 of 1 pings flagged',
    fit 'fitted 1 pings', segment 'segmented 1 pings', convert 'wrote 1 pings', map '1 pings, ...',
    simulate and preprocess 'ping(s)'."""
    one = str(test_ping_paths[7])
    args = {
        "ranges": ["ranges", one, "-o", str(tmp_path / "r.csv"), "-v"],
        "fit": ["fit", one, "-o", str(tmp_path / "f.csv")],
        "segment": ["segment", one, "-o", str(tmp_path / "seg"), "--no-figure"],
        "convert": ["convert", one, "-o", str(tmp_path / "s.zarr")],
        "map": ["map", one, "--static", "-o", str(tmp_path / "m.ply")],
        "simulate": ["simulate", "-o", str(tmp_path / "sim")],
        "preprocess": ["preprocess", one, "-o", str(tmp_path / "pre")],
    }[cmd]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "1 ping" in err and "ping(s)" not in err, err
    assert not re.search(r"(?<![/\d])1 pings", err), err  # the bar's '1/1 pings' is fine


@pytest.mark.slow
def test_segment_figure_title_names_the_file_and_the_ping_in_it(data_dir: Path, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: the Fig.-7 figure of a ping read from a bag was titled 'image:0' (a Kongsberg
    ping 'ping59681', the same for both heads); now the file and the ping in it."""
    import sonarmap.cli.segment as seg

    bag = tmp_path / "oc_bag"
    assert main(["convert", str(data_dir / "oculus" / "one_ping_8bit.raw"), "-o", str(bag), "--to", "bag2",
                 "-q"]) == 0
    titles: list[str] = []
    draw = seg.segment_figure

    def spy(*args: object, title: str = "", **kwargs: object) -> object:
        titles.append(title)
        return draw(*args, title=title, **kwargs)

    monkeypatch.setattr(seg, "segment_figure", spy)
    assert main(["segment", str(bag), "-o", str(tmp_path / "seg"), "-q"]) == 0
    assert titles == ["oc_bag#/sonar/image:0"]


def test_info_gives_the_duration_of_png_pings_too(capsys: pytest.CaptureFixture[str], didson_dir: Path) -> None:
    """Before: 'sonarmap info didson/test' gave time_first_utc / time_last_utc but no duration_s,
    which every recording format gives (the PNG+JSON summary was built on its own)."""
    import json

    assert main(["info", "--json", str(didson_dir / "test")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["pings"] == 10 and d["duration_s"] == pytest.approx(4485.330203)
    keys = list(d)
    assert keys.index("time_first_utc") < keys.index("duration_s") < keys.index("first_ping_zero_fraction")


@pytest.mark.parametrize(("cmd", "extra", "option"), [
    ("segment", ["--method", "threshold", "--solver", "icm"], "--solver"),
    ("ranges", ["--method", "map", "--beta", "1"], "--beta"),
])
def test_mrf_options_with_another_method_are_a_usage_error(cmd: str, extra: list[str], option: str,
                                                           test_ping_paths: list[Path], tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap segment X --method threshold --solver icm' (and --beta with --method map)
    ran without the option, which only the MRF reads, and said nothing."""
    out = tmp_path / "out"
    assert main([cmd, str(test_ping_paths[0]), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert f"Invalid value for {option}: applies to the MRF only" in err and not out.exists()


def test_segment_file_names_are_the_documented_ones(capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Before, neither segment --help nor docs/segmentation.md said how a ping inside a recording
    is named, nor that a Kongsberg ping's files go into a folder per head."""
    from sonarmap.cli.segment import _stem

    assert _stem("/d/test/1468966347175925_raw.png", 0) == "1468966347175925"
    assert _stem("/d/sample.aris#3", 3) == "sample_3"
    assert _stem("/d/0077_20221109_123655_Belgica.all#head2004/ping59681", 0) == \
        "0077_20221109_123655_Belgica_head2004/ping59681"
    monkeypatch.setenv("COLUMNS", "200")
    assert main(["segment", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(sample_3)" in text and "FILE_headID/pingN, a folder per head" in text
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "segmentation.md").read_text().split())
    assert "`0077_20221109_123655_Belgica_head2004/ping59681_labels.png`" in doc
