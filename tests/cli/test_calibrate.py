"""``sonarmap calibrate`` and ``sonarmap fit`` end to end."""

from __future__ import annotations

import pytest

import csv
import json

from sonarmap.cli import main
from sonarmap.geometry import load_geometry


@pytest.mark.slow
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
    assert set(rows[0]) == {"ping", "family", "weights", "scales", "kld", "flags", "gates"}
    assert abs(sum(float(v) for v in rows[0]["weights"].split(";")) - 1) < 1e-6


def test_fit_names_every_ping_of_a_dual_head_recording_apart(data_dir, tmp_path):
    """The two heads of the Kongsberg recording share ping counters: the ping cell keeps the head
    (it was the last path part, 'ping59681', on two rows)."""
    out = tmp_path / "em.csv"
    assert main(["fit", str(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"), "-o", str(out), "-q"]) == 0
    with open(out, newline="") as fh:
        names = [r["ping"] for r in csv.DictReader(fh)]
    assert len(names) == 10 and len(set(names)) == 10
    assert names[:2] == ["0077_20221109_123655_Belgica.all#head2004/ping59681",
                         "0077_20221109_123655_Belgica.all#head2031/ping59681"]


def test_calibrate_aris_recording_and_use_it(data_dir, tmp_path, capsys):
    """Any recording, not only open water: the ARIS file gives the background level vs range and
    beam, and `ranges --calibration` normalises every frame by it."""
    import numpy as np

    out = tmp_path / "aris.json"
    assert main(["calibrate", str(data_dir / "aris" / "sample.aris"), "-o", str(out)]) == 0
    text = capsys.readouterr().err
    assert "not thresholded" in text and "cannot estimate: only 6 pings" in text
    cal = json.loads(out.read_text())["calibration"]
    assert cal["kind"] == "normalised"
    bl = cal["background_level"]
    assert bl["n_pings"] == 6 and not bl["thresholded"] and len(bl["level_by_bin"]) == 2000
    level = np.asarray(bl["level_by_bin"])
    assert 2.5 < level[:100].mean() / level[-100:].mean() < 4.0  # falls ~3x over the window
    assert 3.0 < bl["range_dependence_db"] < 5.0
    assert len(cal["taper"]) == 48 and 0.8 < min(cal["taper"]) <= max(cal["taper"]) < 1.2
    assert cal["model"]["families"][0] in ("exponential", "gamma", "weibull")
    csv_out = tmp_path / "r.csv"
    assert main(["ranges", str(data_dir / "aris" / "sample.aris"), "-o", str(csv_out), "--calibration", str(out)]) == 0
    rows = list(csv.DictReader(csv_out.open()))
    rm = [float(r["range_m"]) for r in rows if r["range_m"]]
    # nothing in the water column in front of the target, whose near end (frame 0, beams 37-39)
    # lies at 15.4 m (the uncalibrated default reports 15.42-15.44 m there)
    assert len(rm) >= 100 and min(rm) > 15.3
    # a calibration of another sonar setting is refused in one line
    oc = tmp_path / "oc.json"
    assert main(["calibrate", str(data_dir / "oculus" / "three_pings_8bit.raw"), "-o", str(oc)]) == 0
    assert main(["ranges", str(data_dir / "aris" / "sample.aris"), "-o", str(csv_out), "--calibration", str(oc)]) == 1


@pytest.mark.slow
def test_map_and_segment_take_the_calibration(data_dir, tmp_path):
    """``map`` and ``segment`` run the pipeline ``ranges --calibration`` runs: the same returns."""
    import numpy as np
    import pandas as pd
    from PIL import Image

    rec = data_dir / "aris" / "sample.aris"
    cal = tmp_path / "aris.json"
    assert main(["calibrate", str(rec), "-o", str(cal), "-q"]) == 0
    assert main(["ranges", str(rec), "-o", str(tmp_path / "r.csv"), "--calibration", str(cal), "-q"]) == 0
    assert main(["ranges", str(rec), "-o", str(tmp_path / "self.csv"), "-q"]) == 0
    assert main(["map", str(rec), "--static", "-o", str(tmp_path / "m.csv"), "--calibration", str(cal), "-q"]) == 0
    ranges = pd.read_csv(tmp_path / "r.csv").dropna(subset=["range_m"])
    own = pd.read_csv(tmp_path / "self.csv").dropna(subset=["range_m"])
    points = pd.read_csv(tmp_path / "m.csv")
    key = ["time_ns", "beam"]
    joined = ranges.merge(points, on=key, suffixes=("", "_map"), validate="one_to_one")
    assert len(joined) == len(ranges) == len(points)
    np.testing.assert_allclose(joined["range_m_map"], joined["range_m"], atol=1e-5)  # the CSV's 6 digits
    # the calibration changes the result (it is used): another set of returns than self-normalised
    assert not own.set_index(key)["range_m"].equals(ranges.set_index(key)["range_m"])
    assert main(["segment", str(rec), "-o", str(tmp_path / "seg"), "--calibration", str(cal), "--no-figure",
                 "-q"]) == 0
    assert len(list((tmp_path / "seg").glob("*_labels.png"))) == 6
    with Image.open(next(iter(sorted((tmp_path / "seg").glob("*_labels.png"))))) as im:
        assert im.size == (48, 2000)
    # a calibration that is not one is refused in one line, before any processing
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    assert main(["map", str(rec), "--static", "-o", str(tmp_path / "x.csv"), "--calibration", str(bad)]) == 1
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.slow
def test_process_takes_the_calibration_and_resumes_only_under_it(data_dir, tmp_path, capsys):
    """``process --calibration`` stores the ranges ``ranges --calibration`` gives; the calibration is
    part of the run's fingerprint (a store is never resumed under another one)."""
    import numpy as np
    import pandas as pd
    import xarray as xr

    rec = data_dir / "aris" / "sample.aris"
    cal = tmp_path / "aris.json"
    assert main(["calibrate", str(rec), "-o", str(cal), "-q"]) == 0
    assert main(["ranges", str(rec), "-o", str(tmp_path / "r.csv"), "--calibration", str(cal), "-q"]) == 0
    store = tmp_path / "p.zarr"
    assert main(["process", str(rec), "-o", str(store), "--calibration", str(cal), "-j", "0", "-q"]) == 0
    ds = xr.open_zarr(store)
    want = pd.read_csv(tmp_path / "r.csv").pivot(index="time_ns", columns="beam", values="range_m")
    got = ds["range"].values
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want.to_numpy(), atol=1e-5, equal_nan=True)  # the CSV's 6 digits
    capsys.readouterr()
    # the same command resumes; without the calibration it is another run, refused in one line
    assert main(["process", str(rec), "-o", str(store), "--calibration", str(cal), "-j", "0"]) == 0
    assert "resumed (1/1 chunks already done)" in capsys.readouterr().err
    assert main(["process", str(rec), "-o", str(store), "-j", "0"]) == 1
    assert "made from different inputs, configuration or options" in capsys.readouterr().err


@pytest.mark.slow
def test_report_processes_its_example_pings_under_the_runs_calibration(data_dir, tmp_path, monkeypatch):
    """A store processed with ``--calibration`` records it (the ``calibration`` attribute), and
    ``report`` re-processes its example pings with it, as the run did (before: without it, so the
    fans and labels drawn under the stored ranges came from another normalisation)."""
    import json

    import zarr

    import sonarmap.pipeline
    from sonarmap.preprocess.normalise import RecordingBackground

    rec = data_dir / "aris" / "sample.aris"
    cal, store = tmp_path / "aris.json", tmp_path / "p.zarr"
    assert main(["calibrate", str(rec), "-o", str(cal), "-q"]) == 0
    assert main(["process", str(rec), "-o", str(store), "--calibration", str(cal), "-j", "0", "-q"]) == 0
    stored = RecordingBackground.from_dict(json.loads(zarr.open_group(str(store), mode="r").attrs["calibration"]))
    given = json.loads(cal.read_text())["calibration"]["background_level"]
    assert stored.to_dict() == RecordingBackground.from_dict(given).to_dict()
    seen = []
    process_ping = sonarmap.pipeline.process_ping

    def spy(ping, config, **kw):
        seen.append(kw.get("background"))
        return process_ping(ping, config, **kw)

    monkeypatch.setattr(sonarmap.pipeline, "process_ping", spy)
    assert main(["report", str(store), "-o", str(tmp_path / "r.html"), "-q"]) == 0
    assert seen and all(b is not None and b.to_dict() == stored.to_dict() for b in seen)
    # a store processed without a calibration has none, and its examples are processed without one
    plain = tmp_path / "plain.zarr"
    assert main(["process", str(rec), "-o", str(plain), "-j", "0", "-q"]) == 0
    assert "calibration" not in zarr.open_group(str(plain), mode="r").attrs
    seen.clear()
    assert main(["report", str(plain), "-o", str(tmp_path / "p.html"), "-q"]) == 0
    assert seen and all(b is None for b in seen)


def test_calibrate_three_ping_oculus_says_what_it_cannot_estimate(data_dir, tmp_path, capsys):
    out = tmp_path / "oc.json"
    assert main(["calibrate", str(data_dir / "oculus" / "three_pings_8bit.raw"), "-o", str(out)]) == 0
    text = capsys.readouterr().err
    assert "cannot estimate: only 3 pings" in text
    assert "window starts at 0 m" in text
    cal = json.loads(out.read_text())["calibration"]
    assert any("only 3 pings" in x for x in cal["not_estimated"])
    assert cal["radial_gain"] is not None  # fitted on the bins beyond 0 m, no log10(0) error


def test_calibrate_water_column_says_why_and_what_instead(data_dir, tmp_path, capsys):
    """Kongsberg water column changes its window every ping: the one error line says what differs
    between which pings, and that ranges and map normalise each ping by itself."""
    out = tmp_path / "em.json"
    rc = main(["calibrate", str(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"), "-o", str(out)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert rc == 1 and not out.exists() and len(err) == 1
    assert "bins x 256 beams where" in err[0] and "#head2004/ping59681 has 458 x 256" in err[0]
    assert "one sonar setting" in err[0] and "ranges and map normalise each ping" in err[0]


def test_calibrate_degenerate_recording_exits_1(tmp_path, test_ping_paths, capsys):
    import numpy as np

    from sonarmap.io import read_pings
    from sonarmap.io.pngjson import write_png_ping

    p = next(iter(read_pings(test_ping_paths[0])))
    write_png_ping(p.replace(image=np.zeros(p.shape, np.float32)), tmp_path, stem="1468966347175925")
    rc = main(["calibrate", str(tmp_path), "-o", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and "error" in err


def test_fit_command_normalises_aris_and_reports_gates(data_dir, tmp_path):
    aris = data_dir / "aris" / "sample.aris"
    out = tmp_path / "a.csv"
    assert main(["fit", str(aris), "-o", str(out), "-m", "em"]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 6
    for r in rows:
        w = [float(v) for v in r["weights"].split(";")]
        assert w[0] > 0.7 and w[1] + w[2] < 0.3 and r["gates"] == ""  # zero spike, plausible
    raw = tmp_path / "raw.csv"
    assert main(["fit", str(aris), "-o", str(raw), "-m", "em", "--no-normalise"]) == 0
    for r in csv.DictReader(raw.open()):
        assert "object_weight" in r["gates"].split(";")  # the old failure, now named


def test_a_calibration_that_cannot_apply_is_refused(data_dir, tmp_path, capsys):
    """Before: 'ranges didson/test --calibration didson.json' (the DIDSON calibration, which is a
    geometry for --sonar) was silently ignored, and 'ranges didson/test --calibration aris.json'
    (an ARIS 2000 x 48 calibration on 512 x 96 DIDSON pings) ran with the ARIS intensity model
    (547 returns instead of 544). Both now exit 1 with one line saying why."""
    didson = str(data_dir / "didson" / "test")
    cal_didson, cal_aris = tmp_path / "didson.json", tmp_path / "aris.json"
    assert main(["calibrate", str(data_dir / "didson" / "background"), "-o", str(cal_didson), "-q"]) == 0
    assert main(["calibrate", str(data_dir / "aris" / "sample.aris"), "-o", str(cal_aris), "-q"]) == 0
    capsys.readouterr()
    out = tmp_path / "r.csv"
    assert main(["ranges", didson, "-o", str(out), "--calibration", str(cal_didson)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"give it with --sonar {cal_didson}, not --calibration" in err
    assert main(["ranges", didson, "-o", str(out), "--calibration", str(cal_aris), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "2000 bins x 48 beams does not fit an image of 512 x 96" in err
    assert f"error: {cal_aris}: a background of" in err  # the file, not the library's argument
    assert not out.exists()


def test_a_background_calibration_given_as_sonar_is_pointed_to_calibration(data_dir, tmp_path, capsys):
    """Before: 'ranges sample.aris --sonar aris.json' (the output of 'calibrate sample.aris') took
    the calibration's geometry and said nothing, so the run was uncalibrated; now one warning line
    says to use --calibration. A DIDSON calibration (a geometry with the taper) is meant for --sonar."""
    didson = data_dir / "didson"
    geometry = json.loads((didson / "didson.json").read_text())
    cal = tmp_path / "cal.json"  # what calibrate writes for a recording without a zero spike
    cal.write_text(json.dumps({**geometry, "calibration": {"kind": "normalised"}}))
    one = str(sorted((didson / "test").glob("*_raw.png"))[0])
    assert main(["fit", one, "-o", str(tmp_path / "f.csv"), "-q", "--sonar", str(cal)]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"give it with --calibration {cal}" in err
    cal.write_text(json.dumps({**geometry, "calibration": {"kind": "thresholded"}}))
    assert main(["fit", one, "-o", str(tmp_path / "f.csv"), "-q", "--sonar", str(cal)]) == 0
    assert capsys.readouterr().err == ""
