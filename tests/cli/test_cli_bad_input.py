"""The CLI on bad input: every processing error one line and exit 1, usage errors exit 2.

A matrix of commands (info, ranges, segment, process, report, map) × inputs (missing, junk,
truncated, mutated, non-regular) must never print "internal error" or a traceback.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from guards import deadline

from sonarmap.cli import main

COMMANDS = ("info", "ranges", "segment", "process", "report", "map")


def _args(cmd: str, inp: Path, out: Path) -> list[str]:
    if cmd == "info":
        return ["info", str(inp)]
    if cmd == "report":
        return ["report", str(inp), "-o", str(out / "r.html")]
    if cmd == "process":
        return ["process", str(inp), "-o", str(out / "s.zarr")]
    if cmd == "map":
        return ["map", str(inp), "-o", str(out / "m.ply")]
    if cmd == "segment":
        return ["segment", str(inp), "-o", str(out / "seg")]
    return ["ranges", str(inp), "-o", str(out / "r.csv")]


def _missing(d: Path, data: Path) -> Path:
    return d / "nope.aris"


def _junk(suffix: str) -> Callable[[Path, Path], Path]:
    def make(d: Path, data: Path) -> Path:
        p = d / f"junk{suffix}"
        p.write_bytes(np.random.default_rng(3).integers(0, 256, 5000, dtype=np.uint8).tobytes())
        return p

    return make


def _truncated_aris(d: Path, data: Path) -> Path:
    p = d / "t.aris"
    p.write_bytes((data / "aris" / "sample.aris").read_bytes()[:700])
    return p


def _truncated_oculus(d: Path, data: Path) -> Path:
    p = d / "t.raw"
    raw = (data / "oculus" / "three_pings_8bit.raw").read_bytes()
    p.write_bytes(raw[:90])
    return p


def _truncated_png(d: Path, data: Path) -> Path:
    src = sorted((data / "didson" / "test").glob("*_raw.png"))[0]
    p = d / src.name
    p.write_bytes(src.read_bytes()[:300])
    shutil.copy2(src.with_name(src.name.replace("_raw.png", ".json")), d)
    return p


def _bad_sidecar(d: Path, data: Path) -> Path:
    src = sorted((data / "didson" / "test").glob("*_raw.png"))[0]
    p = Path(shutil.copy2(src, d))
    side = json.loads(src.with_name(src.name.replace("_raw.png", ".json")).read_text())
    side["num_beams"] = 0
    (d / src.name.replace("_raw.png", ".json")).write_text(json.dumps(side))
    return p


def _absurd_aris(d: Path, data: Path) -> Path:
    raw = bytearray((data / "aris" / "sample.aris").read_bytes())
    # every frame's SamplePeriod (frame-header offset 452, uint32) set to 0xFFFFFFFF
    for off in range(1024, len(raw) - 1024, 1024 + 48 * 2000):
        raw[off + 452 : off + 456] = b"\xff\xff\xff\xff"
    p = d / "absurd.aris"
    p.write_bytes(bytes(raw))
    return p


def _fifo(d: Path, data: Path) -> Path:
    p = d / "pipe.aris"
    os.mkfifo(p)
    return p


def _dev_zero(d: Path, data: Path) -> Path:
    p = d / "zero.oculus"
    p.symlink_to("/dev/zero")
    return p


def _bad_store(d: Path, data: Path) -> Path:
    p = d / "bad.zarr"
    p.mkdir()
    (p / "zarr.json").write_bytes(b'{"zarr_format": 3, "node_type": "group", \xc0')
    return p


def _empty_dir(d: Path, data: Path) -> Path:
    p = d / "empty"
    p.mkdir()
    return p


INPUTS: dict[str, Callable[[Path, Path], Path]] = {
    "missing": _missing,
    "junk.aris": _junk(".aris"),
    "junk.png": _junk("_raw.png"),
    "junk.oculus": _junk(".oculus"),
    "junk.bag": _junk(".bag"),
    "truncated.aris": _truncated_aris,
    "truncated.raw": _truncated_oculus,
    "truncated.png": _truncated_png,
    "sidecar num_beams 0": _bad_sidecar,
    "aris SamplePeriod 0xFFFFFFFF": _absurd_aris,
    "fifo": _fifo,
    "/dev/zero": _dev_zero,
    "corrupt store": _bad_store,
    "empty dir": _empty_dir,
}


@pytest.fixture
def alarm() -> Iterator[None]:
    """Fail instead of hanging forever (a FIFO read blocks)."""
    with deadline(60.0):
        yield


@pytest.mark.parametrize("kind", list(INPUTS))
@pytest.mark.parametrize("cmd", COMMANDS)
@pytest.mark.slow
def test_bad_input_is_one_line_exit_1(cmd: str, kind: str, tmp_path: Path, data_dir: Path,
                                      capsys: pytest.CaptureFixture[str], alarm: None) -> None:
    d = tmp_path / "in"
    d.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    inp = INPUTS[kind](d, data_dir)
    rc = main(_args(cmd, inp, out))
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("sonarmap: warning:")]
    assert "internal error" not in err and "Traceback" not in err, err
    if cmd == "info" and rc == 0:  # info describes what it could read; what it skipped is a warning
        assert any(ln.startswith("sonarmap: warning:") for ln in err.splitlines()), err
        return
    assert rc == 1, f"{cmd} on {kind}: exit {rc}, stderr {err!r}"
    assert len(lines) == 1 and lines[0].startswith("sonarmap: error:"), err


@pytest.mark.parametrize("cmd", COMMANDS)
def test_unknown_option_is_usage_error(cmd: str, tmp_path: Path, data_dir: Path) -> None:
    args = _args(cmd, data_dir / "aris" / "sample.aris", tmp_path) + ["--no-such-option"]
    assert main(args) == 2


def test_warnings_print_as_one_line(tmp_path: Path, data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    raw = (data_dir / "aris" / "sample.aris").read_bytes()
    p = tmp_path / "cut.aris"
    p.write_bytes(raw[: 1024 + 97024 + 5000])  # one frame and a partial one
    assert main(["info", str(p)]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("sonarmap: warning: ") and "incomplete" in err[0], err


@pytest.mark.parametrize("cmd", ["ranges", "convert", "process", "show", "calibrate", "map"])
def test_a_cut_recording_without_a_complete_frame_is_one_error_line(
    cmd: str, tmp_path: Path, data_dir: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    """The warning that the last frame was cut off is told on the error's line, not before it."""
    p = tmp_path / "cut.aris"
    p.write_bytes((data_dir / "aris" / "sample.aris").read_bytes()[:2000])  # file header + part of a frame header
    out = {"convert": "c.zarr", "process": "s.zarr", "show": "s.png", "calibrate": "c.json", "map": "m.ply"}
    assert main([cmd, str(p), "-o", str(tmp_path / out.get(cmd, "r.csv"))]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("sonarmap: error: "), err
    assert "last frame header is incomplete (976 of 1024 bytes)" in err[0], err


def test_a_cut_last_frame_is_one_warning_after_the_run(tmp_path: Path, data_dir: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """With complete frames the run goes on and warns once (the file is opened twice)."""
    p = tmp_path / "cut.aris"
    p.write_bytes((data_dir / "aris" / "sample.aris").read_bytes()[: 1024 + 2 * 97024 + 5000])
    assert main(["ranges", str(p), "-o", str(tmp_path / "r.csv"), "-q"]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == [f"sonarmap: warning: {p}: at byte {1024 + 2 * 97024}: last frame is incomplete "
                   "(5000 of 97024 bytes); skipped"], err


def test_lost_dask_scheduler_is_one_line(tmp_path: Path, data_dir: Path, capfd: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import logging

    from distributed.client import FutureCancelledError

    import sonarmap.survey

    def lost(*args: object, **kwargs: object) -> None:
        # what distributed logs and raises when the scheduler dies mid-run
        logging.getLogger("distributed.client").error("Failed to reconnect to scheduler after 30.00 seconds")
        raise FutureCancelledError("sonarmap-chunk-0", reason="scheduler-connection-lost")

    monkeypatch.setattr(sonarmap.survey, "process_survey", lost)
    rc = main(["process", str(data_dir / "aris" / "sample.aris"), "-o", str(tmp_path / "s.zarr"), "-q",
               "--scheduler", "tcp://127.0.0.1:1"])
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert rc == 1
    assert len(err) == 1 and err[0].startswith("sonarmap: error: dask: FutureCancelledError"), err


@pytest.mark.parametrize("cmd", ["process", "convert"])
def test_water_column_to_a_store_is_refused_with_what_to_use(cmd: str, tmp_path: Path, data_dir: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """Kongsberg water column changes its range window every ping: `process` and `convert` (zarr)
    refuse it before any work, in one line that names the commands that do handle it."""
    out = tmp_path / "k.zarr"
    rc = main([cmd, str(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and not out.exists()
    msg = [ln for ln in err.splitlines() if "error" in ln]
    assert len(msg) == 1 and "every ping" in msg[0] and "sonarmap ranges" in msg[0], err
    assert "Kongsberg" in msg[0] and "kongsberg water" not in msg[0]  # process said 'kongsberg water column'


def test_a_failed_process_prints_no_empty_line_for_its_progress_bar(tmp_path: Path, data_dir: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """On a pipe, the progress bar of a run that fails is dropped whole: stderr holds the reader's
    warning and the error, and no empty line between them."""
    rc = main(["process", str(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"), "-o",
               str(tmp_path / "k.zarr")])
    err = capsys.readouterr().err.splitlines()
    assert rc == 1 and len(err) == 2, err
    assert err[0].startswith("sonarmap: warning:") and err[1].startswith("sonarmap: error:"), err


@pytest.mark.parametrize("cmd", [["ranges"], ["map", "--static"], ["convert"], ["calibrate"]])
def test_a_single_input_without_a_complete_ping_is_named_in_the_error(cmd: list[str], tmp_path: Path, data_dir: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """An ARIS file cut inside its first frame: the error names the file (not the argument PINGS)."""
    cut = tmp_path / "cut.aris"
    cut.write_bytes((data_dir / "aris" / "sample.aris").read_bytes()[:50_000])
    out = tmp_path / ("o.zarr" if cmd[0] == "convert" else "o.csv")
    rc = main([cmd[0], str(cut), "-o", str(out), *cmd[1:]])
    err = capsys.readouterr().err.splitlines()
    assert rc == 1 and not out.exists()
    assert err[-1].startswith(f"sonarmap: error: {cut}: no "), err


def test_preprocess_refuses_to_overwrite_a_ping_of_the_same_time(tmp_path: Path, data_dir: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """The two heads of the Kongsberg recording ping at the same times: preprocess wrote both under
    one time-stamp name, the second replacing the first (10 pings read, 5 left, exit 0)."""
    out = tmp_path / "pp"
    rc = main(["preprocess", str(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"), "-o", str(out)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert rc == 1 and len(err) == 1, err
    assert "#head2031/ping59681: has the time stamp of" in err[0] and "#head2004/ping59681" in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["1667997414649000.json", "1667997414649000_raw.png"]
