"""HTML survey report: self-contained, and renders in headless Chromium without page errors."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from browser import page_errors, screenshot
from sonarmap.report import ReportConfig, build_report, render_report
from sonarmap.survey import process_survey, replicate_pings


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory, test_ping_paths: list[Path]) -> Path:
    d = tmp_path_factory.mktemp("report")
    pings = replicate_pings(test_ping_paths, 30, d / "pings")
    out = d / "survey.zarr"
    process_survey([pings], out, workers=0, chunk_size=10)
    return out


@pytest.fixture(scope="module")
def report_html(store: Path) -> Path:
    return build_report(store, store.parent / "report.html", config=ReportConfig(n_examples=2, dpi=60))


@pytest.mark.slow
def test_report_is_self_contained(report_html: Path) -> None:
    text = report_html.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>")
    for section in ("Summary", "Mixture parameters", "ROC curves", "Flagged pings", "Example pings"):
        assert section in text
    assert "<td>30</td>" in text  # number of pings in the summary
    # Every resource is inline: no scripts, stylesheets links or external URLs.
    srcs = re.findall(r'src="([^"]*)"', text)
    assert len(srcs) == 6  # time series, ranges, range uncertainty, ROC, 2 example pings (no map: no poses)
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "<script" not in text and "<link" not in text and "http://" not in text
    assert "https://" not in text
    # The embedded images decode as PNG.
    import base64

    for s in srcs:
        assert base64.b64decode(s.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_report_draws_example_fans(report_html: Path) -> None:
    text = report_html.read_text(encoding="utf-8")
    assert text.count('alt="ping ') == 2
    assert "not drawn" not in text


@pytest.mark.slow
def test_report_renders_in_headless_chromium(report_html: Path, tmp_path: Path) -> None:
    from PIL import Image

    png = tmp_path / "shot.png"
    log = screenshot(report_html, png)
    assert page_errors(log) == []
    img = np.asarray(Image.open(png).convert("L"), dtype=np.float64)
    assert img.shape == (2000, 1280)
    # Not blank: text and figures give many dark pixels and a broad spread of grey levels.
    assert (img < 128).mean() > 0.01
    assert img.std() > 20


@pytest.mark.slow  # starts a child process
def test_page_error_detection_works(tmp_path: Path) -> None:
    """The check above would catch a broken page (guards against a silently weak test)."""
    bad = tmp_path / "bad.html"
    bad.write_text("<html><body>x<script>undefinedFunction();</script></body></html>")
    log = screenshot(bad, tmp_path / "bad.png")
    assert any("undefinedFunction" in e for e in page_errors(log))


@pytest.mark.slow
def test_report_refuses_to_overwrite(store: Path, report_html: Path) -> None:
    from sonarmap.errors import DataFormatError

    with pytest.raises(DataFormatError, match="overwrite"):
        build_report(store, report_html)
    assert render_report(store, config=ReportConfig(n_examples=0)).count("<img") >= 3


@pytest.mark.slow
def test_cli_report(store: Path, tmp_path: Path) -> None:
    out = tmp_path / "r.html"
    r = subprocess.run([sys.executable, "-m", "sonarmap", "report", str(store), "-o", str(out),
                        "--examples", "0"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert out.exists() and str(out) in r.stderr and r.stdout == ""
    r = subprocess.run([sys.executable, "-m", "sonarmap", "report", str(store), "-o", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "--overwrite" in r.stderr
    r = subprocess.run([sys.executable, "-m", "sonarmap", "report", str(tmp_path), "-o", str(tmp_path / "x.html")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "not a sonarmap survey store" in r.stderr


def test_chance_diagonal_is_drawn_densely_on_the_log_axis() -> None:
    """pD = pFA from 0 to 1, with log-spaced points: on the report's symlog pFA axis two end
    points would be joined by a straight segment in display space (pD 0.5 drawn at pFA 1e-3)."""
    from sonarmap.report import chance_diagonal

    x, y = chance_diagonal()
    np.testing.assert_array_equal(x, y)
    assert x[0] == 0.0 and x[-1] == 1.0 and x[1] <= 1e-3
    assert np.all(np.diff(x) > 0) and np.max(x[2:] / x[1:-1]) < 1.1


def test_component_scales_hide_components_without_pixels() -> None:
    """A component holding almost no pixels (the object class of a ping without objects, its
    scale at a bound) is not drawn; the last finite parameter is the scale."""
    from sonarmap.report import MIN_SCALE_WEIGHT, component_scales

    param = np.array([[[np.nan, np.nan], [0.02, np.nan], [2.0, 0.15]],
                      [[np.nan, np.nan], [0.03, np.nan], [2.0, 1.0]]])
    weight = np.array([[0.6, 0.35, 0.05], [0.7, 0.3, MIN_SCALE_WEIGHT / 2]])
    s = component_scales(param, weight)
    assert np.isnan(s[:, 0]).all()
    np.testing.assert_allclose(s[:, 1], [0.02, 0.03])
    assert s[0, 2] == 0.15 and np.isnan(s[1, 2])


def test_colour_bar_labels_keep_clear_of_the_next_axis(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ranges and map figures: a colour bar's label and the label of the axis to its right are
    at least 0.3 inch apart (they touched before), and the top view has its own colour bar."""
    import io

    import xarray as xr

    import sonarmap.report as rep

    figs: list = []
    monkeypatch.setattr(rep, "_png", lambda fig, dpi: figs.append(fig) or "")
    rng = np.random.default_rng(0)
    n, b, m = 40, 96, 3000
    ds = xr.Dataset({
        "range": (("ping_time", "beam"), 6 + 0.3 * rng.random((n, b))),
        "beam_azimuth": (("beam",), np.deg2rad(np.linspace(-14, 14, b))),
        "point_xyz": (("point", "xyz"), np.c_[4 * rng.random(m), 6 + 0.2 * rng.random(m), 0.5 + 3.3 * rng.random(m)]),
    })
    rep._fig_ranges(ds, 100)
    rep._fig_map(ds, 5000, 100)
    for fig in figs:
        fig.savefig(io.BytesIO(), format="png", dpi=100)
        r = fig._get_renderer()
        colour_bar = fig.axes[2]  # added after the two axes
        gap = fig.axes[1].yaxis.label.get_window_extent(r).x0 - colour_bar.yaxis.label.get_window_extent(r).x1
        assert gap >= 30, gap
    assert len(figs[1].axes) == 4 and figs[1].axes[3].get_ylabel() == "down z (m)"


@pytest.mark.slow
def test_examples_of_a_store_processed_from_a_converted_store_show_their_own_ping(
        data_dir: Path, tmp_path: Path) -> None:
    """A product store processed from a ``sonarmap convert`` store records each ping's source file
    without its frame (``sample.aris``); the example fans drew frame 0 of that file for every
    example before. Each example now reads its own ping (``sample.aris#k`` for ``ping k``)."""
    from sonarmap.io import read_pings
    from sonarmap.store import write_survey

    raw = tmp_path / "aris.zarr"
    write_survey(read_pings(data_dir / "aris" / "sample.aris"), raw)
    products = tmp_path / "products.zarr"
    process_survey([raw], products, workers=0)
    page = render_report(products, config=ReportConfig(n_examples=3, dpi=40))
    heads = re.findall(r"<h3>ping (\d+): <code>([^<]+)</code></h3>", page)
    assert len(heads) == 3
    for index, name in heads:
        assert name == f"sample.aris#{index}"


def test_the_ranges_figure_numbers_pings_with_whole_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: a 3-ping survey's per-beam range panel had ping ticks 0.0, 0.5, ..., 3.0 and ping i
    spanned [i, i + 1]; now whole-number ticks at the middle of each ping's column."""
    import xarray as xr

    import sonarmap.report as rep

    figs: list = []
    monkeypatch.setattr(rep, "_png", lambda fig, dpi: figs.append(fig) or "")
    ds = xr.Dataset({"range": (("ping_time", "beam"), 1 + np.random.default_rng(0).random((3, 16))),
                     "beam_azimuth": (("beam",), np.deg2rad(np.linspace(-30, 30, 16)))})
    rep._fig_ranges(ds, 60)
    ax = figs[0].axes[0]
    figs[0].canvas.draw()
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks == [0, 1, 2] and ax.images[0].get_extent()[:2] == [-0.5, 2.5]


def test_the_mixture_time_series_says_what_its_x_axis_is(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: the three stacked panels (weights, scales, KLD) shared an x axis of dates with no
    label; the bottom one now says 'ping time (UTC)'."""
    import xarray as xr

    import sonarmap.report as rep

    figs: list = []
    monkeypatch.setattr(rep, "_png", lambda fig, dpi: figs.append(fig) or "")
    n = 4
    t = np.datetime64("2024-05-01T10:20:30", "ns") + np.arange(n) * np.timedelta64(100, "ms")
    ds = xr.Dataset({"mixture_weight": (("ping_time", "component"), np.full((n, 3), 1 / 3)),
                     "mixture_param": (("ping_time", "component", "param"), np.ones((n, 3, 1))),
                     "kld": (("ping_time",), np.full(n, 0.01)),
                     "flags": (("ping_time",), np.array([""] * n, dtype=object))},
                    coords={"ping_time": t})
    rep._fig_timeseries(ds, 60)
    assert figs[0].axes[2].get_xlabel() == "ping time (UTC)"


def test_pings_without_a_time_span_are_drawn_by_index_with_markers(monkeypatch: pytest.MonkeyPatch) -> None:
    """One ping (or pings without a clock, all at one time): the panels drew lines of one point
    (nothing visible) on a date axis spanning four years around it; now one marker per ping, on
    an axis of ping numbers."""
    import xarray as xr

    import sonarmap.report as rep

    figs: list = []
    monkeypatch.setattr(rep, "_png", lambda fig, dpi: figs.append(fig) or "")
    for n in (1, 3):
        ds = xr.Dataset({"mixture_weight": (("ping_time", "component"), np.full((n, 3), 1 / 3)),
                         "mixture_param": (("ping_time", "component", "param"), np.ones((n, 3, 1))),
                         "kld": (("ping_time",), np.full(n, 0.01)),
                         "flags": (("ping_time",), np.array([""] * n, dtype=object))},
                        coords={"ping_time": np.zeros(n, "datetime64[ns]")})
        rep._fig_timeseries(ds, 60)
        ax = figs[-1].axes[2]
        assert ax.get_xlabel() == "ping (the pings have no time span)"
        assert list(ax.lines[0].get_xdata()) == list(range(n)) and ax.lines[0].get_marker() == "o"
        assert figs[-1].axes[0].lines[0].get_marker() == "o"


@pytest.mark.slow
def test_examples_of_pings_read_with_a_given_geometry_are_drawn(didson_dir: Path, tmp_path: Path) -> None:
    """A PNG ping without a sidecar JSON is processed with a geometry given (``--sonar``); the
    report read it again without one and printed 'not drawn (no sidecar JSON ...)' instead of
    the example.  It now reads it with the store's geometry."""
    img = tmp_path / "pings" / "tuna_can.png"
    img.parent.mkdir()
    img.symlink_to(didson_dir / "extra" / "tuna_can.png")
    products = tmp_path / "products.zarr"
    process_survey([img.parent], products, workers=0, geometry=didson_dir / "didson.json")
    page = render_report(products, config=ReportConfig(n_examples=1, dpi=40))
    assert "not drawn" not in page
    assert re.findall(r"<h3>ping (\d+): <code>([^<]+)</code></h3>", page) == [("0", "tuna_can.png")]


def test_fan_aspect_of_the_shared_sonars(data_dir: Path, didson_dir: Path) -> None:
    from sonarmap.io import read_ping
    from sonarmap.plots import fan_aspect

    aris = read_ping(data_dir / "aris" / "sample.aris").geometry
    oculus = read_ping(data_dir / "oculus" / "one_ping_8bit.raw").geometry
    didson = read_ping(next((didson_dir / "test").glob("*_raw.png"))).geometry
    assert fan_aspect(aris) == pytest.approx(0.303, abs=0.005)  # 14.6 deg, 3.3-23.4 m
    assert fan_aspect(didson) == pytest.approx(0.622, abs=0.005)
    assert fan_aspect(oculus) == pytest.approx(1.004, abs=0.01)


@pytest.mark.slow
def test_narrow_fans_are_drawn_as_their_polar_images(data_dir: Path, store: Path, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The ARIS telephoto fan drawn to scale was a sliver a quarter of its panel wide; its example
    pings are now its images as stored (beams across, range up), with the returns on them.  The
    DIDSON examples stay fans."""
    import sonarmap.report as rep

    figs: list = []
    monkeypatch.setattr(rep, "_png", lambda fig, dpi: figs.append(fig) or "")
    products = tmp_path / "aris.zarr"
    process_survey([data_dir / "aris" / "sample.aris"], products, workers=0)
    render_report(products, config=ReportConfig(n_examples=1, dpi=40))
    ex = [f for f in figs if len(f.axes) == 3 and f.axes[2].get_title() == "segmented + ranges"]
    assert len(ex) == 1
    ax = ex[0].axes[2]
    assert ax.get_xlabel().startswith("beam (azimuth") and ax.get_ylabel() == "range (m)"
    x, y = ax.lines[0].get_data()
    assert len(x) >= 40 and 15.0 <= np.median(y) <= 18.0  # the target's returns, in metres
    figs.clear()
    render_report(store, config=ReportConfig(n_examples=1, dpi=40))
    ex = [f for f in figs if len(f.axes) == 3 and f.axes[2].get_title() == "segmented + ranges"]
    assert ex and ex[0].axes[0].get_xlabel() == "starboard y (m)"


def test_the_uncertainty_figure_and_row_show_the_returns_sigma_per_beam(monkeypatch: pytest.MonkeyPatch) -> None:
    """The returns' range sigma per beam (median and 16-84 % over the pings, only where the beam
    has a return; cm, with a range-bin axis when the bin spacing is known) and each beam's median
    p_detect; the summary row gives the median and 5-95 % over all returns; nothing is drawn for a
    store without either variable (stores written before they existed)."""
    import json

    import xarray as xr

    import sonarmap.report as rep

    figs: list = []
    monkeypatch.setattr(rep, "_png", lambda fig, dpi: figs.append(fig) or "png")
    rng = np.random.default_rng(1)
    n, b = 20, 12
    rng_m = 5 + rng.random((n, b))
    rng_m[:, 3] = np.nan  # a beam without returns
    rng_m[::2, 5] = np.nan  # a beam with returns on half the pings
    sigma = 0.002 + 0.01 * rng.random((n, b))
    sigma[::2, 5] = 5.0  # (the sigma stored on a ping without a return is not the beam's)
    pdet = np.tile(np.linspace(0.2, 0.9, b), (n, 1))
    ds = xr.Dataset({
        "range": (("ping_time", "beam"), rng_m),
        "range_sigma": (("ping_time", "beam"), sigma),
        "p_detect": (("ping_time", "beam"), pdet),
        "beam_azimuth": (("beam",), np.deg2rad(np.linspace(-10, 10, b))),
    })
    assert rep._fig_uncertainty(ds, 0.004, 60) == "png"
    ax, axp = figs[0].axes[0], figs[0].axes[1]
    med = ax.lines[0].get_ydata()
    want = np.nanmedian(np.where(np.isfinite(rng_m), sigma, np.nan), axis=0) * 100
    assert np.allclose(med, want, equal_nan=True) and np.isnan(med[3]) and med[5] < 2.0
    assert np.allclose(axp.lines[0].get_ydata(), np.linspace(0.2, 0.9, b))
    assert any(getattr(a, "get_ylabel", lambda: "")() == "range bins" for a in ax.child_axes)

    attrs = {"source_geometry": json.dumps({"min_range": 1.0, "max_range": 5.0, "num_bins": 1001})}
    assert rep._bin_m(attrs) == pytest.approx(0.004)
    assert rep._bin_m({}) is None and rep._bin_m({"source_geometry": "{bad"}) is None
    assert rep._bin_m({"source_geometry": json.dumps({"min_range": 1.0, "max_range": 1.0, "num_bins": 5})}) is None
    finite = sigma[np.isfinite(rng_m)] * 100
    row = rep._sigma_summary(ds, 0.004)
    assert row.startswith(f"{np.median(finite):.3g} cm (5-95 %: {np.percentile(finite, 5):.3g}-")
    assert row.endswith(f"; {np.median(finite) / 0.4:.3g} range bins")
    assert rep._sigma_summary(ds, None).endswith(" cm)")
    old = ds.drop_vars(["range_sigma", "p_detect"])
    assert rep._fig_uncertainty(old, 0.004, 60) is None and rep._sigma_summary(old, 0.004) == "-"
