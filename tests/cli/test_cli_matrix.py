"""The CLI matrix: every registered command's help, usage errors, progress and quiet mode.

For every command of ``sonarmap.cli.app``: ``--help`` shows an example and plain types (no
``<bool>``, ``<list[Path]>``, RST markup or internal names); a bad option value exits 2 before any
work; ``-q`` silences the progress bar and summary on stderr, which are drawn without it; results
go to stdout only with ``-o -``.  Inputs: two real DIDSON pings copied to ``tmp_path``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import typer.main

from sonarmap.cli import app, main

#: Every command registered on the app (the modules of COMMAND_MODULES that exist).
COMMANDS = sorted(typer.main.get_command(app).commands)  # type: ignore[attr-defined]

#: (command, check) pairs known not to meet the matrix yet (expected failures, not strict).
PENDING: dict[tuple[str, str], str] = {}


def _param(cmd: str, check: str) -> object:
    """``cmd`` as a pytest parameter, expected to fail while its (command, check) is pending."""
    reason = PENDING.get((cmd, check))
    if reason is not None:
        return pytest.param(cmd, marks=pytest.mark.xfail(reason=reason, strict=False))
    return cmd


def _help(cmd: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setenv("COLUMNS", "200")
    assert main([cmd, "--help"]) == 0
    return capsys.readouterr().out


def _lines(err: str) -> list[str]:
    """stderr lines that are not one-line warnings."""
    return [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("sonarmap: warning:")]


@pytest.fixture
def two_pings(tmp_path: Path, test_ping_paths: list[Path]) -> Path:
    """A directory with two real DIDSON pings (PNG + JSON sidecars)."""
    d = tmp_path / "pings"
    d.mkdir()
    for p in test_ping_paths[:2]:
        shutil.copy2(p, d)
        shutil.copy2(p.with_name(p.name.replace("_raw.png", ".json")), d)
    return d


def test_matrix_covers_every_command() -> None:
    assert {"ranges", "segment", "map", "fit", "preprocess", "calibrate", "convert"} <= set(COMMANDS)
    assert len(COMMANDS) >= 14


@pytest.mark.parametrize("cmd", [_param(c, "example") for c in COMMANDS])
def test_help_has_an_example(cmd: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    text = _help(cmd, capsys, monkeypatch)
    assert "Example:" in text and f"sonarmap {cmd}" in text.split("Example:", 1)[1], text


#: What a user should never see in --help: Python annotation labels, RST roles and literals,
#: names of internal classes and functions.
FORBIDDEN_IN_HELP = ("<bool>", "<list", "<Path>", "<str>", "<int>", "<float>", "``", ":class:", ":func:", ":data:",
                     "PipelineConfig", "load_geometry", "typer", "NoneType")


@pytest.mark.parametrize("cmd", [_param(c, "plain") for c in COMMANDS])
def test_help_is_plain(cmd: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    text = _help(cmd, capsys, monkeypatch)
    bad = [s for s in FORBIDDEN_IN_HELP if s in text]
    assert not bad, f"{cmd} --help shows {bad}:\n{text}"
    assert "`" not in text, text  # no Markdown/RST code spans


@pytest.mark.parametrize("cmd", [_param(c, "narrow") for c in COMMANDS])
def test_help_on_an_80_column_terminal_cuts_no_word(cmd: str, capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A help word wider than its column is folded onto the next line, never cut with an
    ellipsis (before, at 80 columns: map's --poses 'time_ns|time_s,x,y,z,q…', --extrinsics,
    --format; convert's --start-time example time; live's --bag message type)."""
    monkeypatch.setenv("COLUMNS", "80")
    assert main([cmd, "--help"]) == 0
    text = capsys.readouterr().out
    assert "\u2026" not in text, text
    if cmd == "map":
        assert "qw" in text and "rpy_deg" in text


def test_quiet_and_verbose_are_where_the_readme_says(capsys: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """README: -q on every command but info, -v on the commands it lists. Before it said every
    command had both, and 'sonarmap show ... -q' was a usage error (show had neither)."""
    readme = " ".join((Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8").split())
    listed = readme.split("The commands that go through pings one by one (", 1)[1].split(")", 1)[0]
    verbose = {name.strip(" `") for name in listed.split(",")}
    for cmd in COMMANDS:
        text = _help(cmd, capsys, monkeypatch)
        assert ("--quiet" in text) == (cmd != "info"), cmd
        assert ("--verbose" in text) == (cmd in verbose), cmd


def test_show_quiet_prints_nothing(test_ping_paths: list[Path], tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "fan.png"
    assert main(["show", str(test_ping_paths[0]), "-o", str(out), "-q"]) == 0
    assert out.exists() and capsys.readouterr().err == ""


#: Commands whose -o writes files or stores; '-' (stdout) is a usage error there.
FILE_OUTPUT_COMMANDS = ("segment", "preprocess", "simulate", "convert", "process", "report", "paper", "demo", "live")


@pytest.mark.parametrize("cmd", FILE_OUTPUT_COMMANDS)
def test_stdout_output_is_refused_where_files_are_written(cmd: str, two_pings: Path, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap segment X -o -' (and simulate, convert, process, preprocess, paper, demo)
    ran and wrote a directory or store named '-' in the working directory."""
    monkeypatch.chdir(tmp_path)
    args = {"simulate": ["simulate"], "demo": ["demo"], "paper": ["paper", "--data", str(two_pings)],
            "report": ["report", str(two_pings)], "live": ["live", str(two_pings), "--replay"]}.get(cmd, [cmd, str(two_pings)])
    assert main([*args, "-o", "-"]) == 2
    err = capsys.readouterr().err
    assert "'-' (stdout) is only for ranges, fit, calibrate and map" in err and "━" not in err
    assert not (tmp_path / "-").exists()


def test_help_types_are_click_style(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    text = _help("ranges", capsys, monkeypatch)
    assert "Usage: sonarmap ranges [OPTIONS] PINGS..." in text

    def row(option: str) -> list[str]:
        line = next(ln for ln in text.splitlines() if f" {option} " in ln)
        return line.split()

    assert "PATH" in row("--output") and "FLOAT" in row("--beta") and "PRESET|JSON" in row("--sonar")
    strict = row("--strict")
    assert strict[strict.index("--strict") + 1] == "Exit"  # a flag takes no value: no type column


def _bad_value(cmd: str, pings: Path, out: Path) -> list[str]:
    """A command line of ``cmd`` with one invalid option value."""
    table: dict[str, list[str]] = {
        "info": ["info", "--sonar", "no-such-preset", str(pings)],
        "show": ["show", str(next(pings.glob("*_raw.png"))), "-o", str(out / "x.xyz")],
        "simulate": ["simulate", "--scene", "no-such-scene", "-o", str(out / "sim")],
        "calibrate": ["calibrate", str(pings), "-o", str(out / "c.json"), "--method", "nope"],
        "preprocess": ["preprocess", str(pings), "-o", str(out / "pre"), "--recipe", "nope"],
        "fit": ["fit", str(pings), "-o", str(out / "f.csv"), "--families", "exponential,nope"],
        "paper": ["paper", "--data", str(out / "no-such-dir"), "-o", str(out / "paper")],
        "segment": ["segment", str(pings), "-o", str(out / "seg"), "--solver", "nope"],
        "ranges": ["ranges", str(pings), "-o", str(out / "r.csv"), "--method", "nope"],
        "map": ["map", str(pings), "-o", str(out / "m.ply"), "--static", "--frame", "up"],
        "convert": ["convert", str(pings), "-o", str(out / "s.zarr"), "--to", "tar"],
        "process": ["process", str(pings), "-o", str(out / "s.zarr"), "--sonar", "no-such-preset"],
        "live": ["live", str(pings), "--replay", "--queue", "0", "-o", str(out / "s.zarr")],
        "report": ["report", str(out / "s.zarr"), "-o", str(out / "r.html"), "--examples", "-1"],
        "demo": ["demo", "-o", str(out / "demo"), "--pings", "1"],
    }
    return table[cmd]


@pytest.mark.parametrize("cmd", [_param(c, "usage") for c in COMMANDS])
def test_bad_option_value_exits_2_before_work(cmd: str, two_pings: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    assert main(_bad_value(cmd, two_pings, out)) == 2
    err = capsys.readouterr().err
    assert "Invalid value" in err or "Error" in err, err
    assert "━" not in err  # no progress bar: nothing ran
    assert sorted(p.name for p in out.iterdir()) == []  # nothing written


#: Commands with a ``--sonar`` option: an unknown preset is a usage error that lists the presets.
SONAR_COMMANDS = ("info", "calibrate", "preprocess", "fit", "segment", "ranges", "map", "convert", "process",
                  "simulate")


@pytest.mark.parametrize("cmd", SONAR_COMMANDS)
def test_unknown_preset_lists_the_presets(cmd: str, two_pings: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    args = {"info": ["info", str(two_pings)], "simulate": ["simulate", "-o", str(tmp_path / "sim")]}.get(
        cmd, [cmd, str(two_pings), "-o", str(tmp_path / "o.out")])
    if cmd == "map":
        args = [cmd, str(two_pings), "-o", str(tmp_path / "m.ply"), "--static"]
    assert main([*args, "--sonar", "didson-lf"]) == 2
    err = capsys.readouterr().err
    assert "didson-lf" in err and "didson-hf" in err and "aris3000-128" in err, err
    assert "No such file" not in err and "no such file" not in err


def _run_args(cmd: str, pings: Path, out: Path) -> list[str]:
    """A small real run of ``cmd`` over the two pings (or two simulated pings)."""
    table: dict[str, list[str]] = {
        "simulate": ["simulate", "--count", "2", "-o", str(out / "sim")],
        "calibrate": ["calibrate", str(pings), "-o", str(out / "c.json")],
        "preprocess": ["preprocess", str(pings), "-o", str(out / "pre")],
        "fit": ["fit", str(pings), "-o", str(out / "f.csv")],
        "segment": ["segment", str(pings), "-o", str(out / "seg"), "--no-figure"],
        "ranges": ["ranges", str(pings), "-o", str(out / "r.csv"), "--method", "threshold"],
        "map": ["map", str(pings), "-o", str(out / "m.ply"), "--static"],
        "convert": ["convert", str(pings), "-o", str(out / "s.zarr")],
        "process": ["process", str(pings), "-o", str(out / "s.zarr"), "--workers", "0", "--chunk-size", "1"],
    }
    return table[cmd]


PROGRESS_COMMANDS = ("simulate", "calibrate", "preprocess", "fit", "segment", "ranges", "map", "convert", "process")


@pytest.mark.parametrize("cmd", PROGRESS_COMMANDS)
@pytest.mark.slow
def test_progress_on_stderr_and_quiet_silences_it(cmd: str, two_pings: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    loud, quiet = tmp_path / "loud", tmp_path / "quiet"
    loud.mkdir()
    quiet.mkdir()
    assert main(_run_args(cmd, two_pings, loud)) == 0
    cap = capsys.readouterr()
    assert "2/2" in cap.err, cap.err  # the bar, completed (stderr is not a terminal here)
    assert cap.out == "", cap.out  # bar and summary on stderr: stdout carries results only with -o -
    assert main([*_run_args(cmd, two_pings, quiet), "-q"]) == 0
    cap = capsys.readouterr()
    assert _lines(cap.err) == [], cap.err
    assert cap.out == "", cap.out  # -q: no summary on either stream (these commands write files)
    assert sorted(p.name for p in quiet.iterdir()) == sorted(p.name for p in loud.iterdir())


@pytest.mark.parametrize("cmd", ("ranges", "segment", "fit", "preprocess", "map", "convert", "simulate",
                                 "calibrate"))
def test_verbose_prints_per_ping_lines_and_time(cmd: str, two_pings: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*_run_args(cmd, two_pings, tmp_path), "-v"]) == 0
    err = capsys.readouterr().err
    assert f"{cmd}: 2 pings in " in err and " s" in err, err
    per_ping = [ln for ln in err.splitlines() if "1468966347175925" in ln or "ping 0" in ln]
    assert per_ping, err


@pytest.mark.parametrize("cmd", ("ranges", "fit", "calibrate", "map"))
def test_results_on_stdout_only_with_dash(cmd: str, two_pings: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    args = _run_args(cmd, two_pings, tmp_path)
    if cmd == "map":
        args = [*args, "--format", "csv"]
    out_file = Path(args[args.index("-o") + 1])
    assert main(args) == 0
    to_file = capsys.readouterr()
    expected = out_file.read_text(encoding="utf-8")
    assert to_file.out == ""
    args[args.index("-o") + 1] = "-"
    assert main(args) == 0
    cap = capsys.readouterr()
    assert cap.out.replace("\r\n", "\n") == expected.replace("\r\n", "\n")
    assert "━" in cap.err or "2/2" in cap.err  # progress and summary stay on stderr
    assert not (tmp_path / "-").exists()


@pytest.mark.parametrize("cmd", ("fit", "preprocess", "calibrate", "convert", "segment", "ranges"))
def test_unreadable_input_is_the_only_line(cmd: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.aris"
    junk.write_bytes(b"\x00\x01junk" * 200)
    out = tmp_path / "out"
    out.mkdir()
    args = _run_args(cmd, junk, out)
    assert main(args) == 1
    lines = _lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("sonarmap: error:"), lines


@pytest.mark.parametrize("cmd", ("ranges", "segment", "fit", "preprocess"))
def test_error_after_some_pings_drops_the_bar(cmd: str, two_pings: Path, tmp_path: Path, data_dir: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A later input that fails mid-run: the error is the only line (the bar is removed)."""
    cut = tmp_path / "cut.aris"
    cut.write_bytes((data_dir / "aris" / "sample.aris").read_bytes()[:700])
    args = _run_args(cmd, two_pings, tmp_path)
    args.insert(2, str(cut))
    assert main(args) == 1
    lines = _lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("sonarmap: error:"), lines


def test_ping_progress_quiet_and_failed_draw_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli._common import ping_progress

    with ping_progress("x", 2, quiet=True) as bar:
        bar.start()
        bar.advance(2)
    assert capsys.readouterr().err == "" and bar.done == 2
    with pytest.raises(RuntimeError), ping_progress("x", 2) as bar:
        bar.start()
        bar.advance()
        raise RuntimeError("boom")
    assert capsys.readouterr().err == ""
    with ping_progress("x", None) as bar:
        bar.start()
        bar.advance(3)
    assert "3/3" in capsys.readouterr().err


def test_map_dash_needs_a_format(two_pings: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["map", str(two_pings), "--static", "-o", "-"]) == 2
    cap = capsys.readouterr()
    assert "--format" in cap.err and cap.out == ""


@pytest.mark.slow  # over a second in the fast subset
def test_convert_refuses_an_existing_output_unless_overwrite_or_append(two_pings: Path, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.io import zarrstore

    out = tmp_path / "s.zarr"
    assert main(["convert", str(two_pings), "-o", str(out), "-q"]) == 0
    assert main(["convert", str(two_pings), "-o", str(out), "-q"]) == 1
    err = _lines(capsys.readouterr().err)
    assert len(err) == 1 and "--overwrite" in err[0] and "--append" in err[0], err
    assert zarrstore.count_pings(out) == 2
    assert main(["convert", str(two_pings), "-o", str(out), "-q", "--append"]) == 0
    assert zarrstore.count_pings(out) == 4
    assert main(["convert", str(two_pings), "-o", str(out), "-q", "--overwrite"]) == 0
    assert zarrstore.count_pings(out) == 2
    assert main(["convert", str(two_pings), "-o", str(out), "--overwrite", "--append"]) == 2


@pytest.mark.slow
def test_report_quiet(two_pings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    store = tmp_path / "s.zarr"
    assert main(["process", str(two_pings), "-o", str(store), "--workers", "0", "-q"]) == 0
    assert main(["report", str(store), "-o", str(tmp_path / "r.html"), "--examples", "0", "-q"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and _lines(cap.err) == []
    assert main(["report", str(store), "-o", str(tmp_path / "r2.html"), "--examples", "0"]) == 0
    assert "r2.html" in capsys.readouterr().err


#: The overwrite policy: a result file (or the files in an output directory) is replaced
#: atomically; a store, report or demo directory needs --overwrite.  Each help says which.
OVERWRITE_POLICY = {
    "ranges": "replaced atomically", "fit": "replaced atomically", "calibrate": "replaced atomically",
    "map": "replaced atomically", "segment": "replaced atomically", "preprocess": "replaced atomically",
    "simulate": "replaced", "paper": "replaced", "convert": "--overwrite", "process": "--overwrite",
    "report": "--overwrite", "demo": "--overwrite",
}


@pytest.mark.parametrize("cmd", sorted(OVERWRITE_POLICY))
def test_help_states_the_overwrite_policy(cmd: str, capsys: pytest.CaptureFixture[str],
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    text = " ".join(_help(cmd, capsys, monkeypatch).split())
    assert OVERWRITE_POLICY[cmd] in text, text
