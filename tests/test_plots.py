"""Figures: the colour scale of ``sonarmap show``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.plots import DB_WINDOW, display_scale, show_ping_figure


def test_auto_scale_is_db_only_for_a_ping_spanning_more_than_30_db() -> None:
    rng = np.random.default_rng(0)
    speckle = rng.exponential(0.1, (200, 32)).astype(np.float32)  # an imaging sonar's 8-bit-like span
    assert display_scale(speckle) == "linear"
    # a water column in dB made linear: -60 dB background, a 0 dB seabed
    wc = (10.0 ** (rng.normal(-60.0, 5.0, (200, 32)) / 10.0)).astype(np.float32)
    wc[150:152] = 1.0
    assert display_scale(wc) == "db"
    assert display_scale(wc, "linear") == "linear" and display_scale(speckle, "db") == "db"
    assert display_scale(np.zeros((4, 4), np.float32)) == "linear"
    with pytest.raises(InputError, match="scale"):
        display_scale(wc, "log")


def test_db_figure_shows_the_window_below_the_maximum(data_dir: Path) -> None:
    from sonarmap.io import read_ping

    p = read_ping(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.wcd", index=0)
    fig = show_ping_figure(p, polar=True)
    fan, polar = (ax.images[0] for ax in fig.axes[:2])
    lo, hi = fan.get_clim()
    assert hi - lo == pytest.approx(DB_WINDOW)
    pos = p.image[p.image > 0]
    assert hi == pytest.approx(10 * np.log10(np.percentile(pos, 99.9)), abs=0.5)
    assert polar.get_clim() == (lo, hi)
    assert any(getattr(ax, "get_ylabel", lambda: "")() == "intensity (dB)" for ax in fig.axes)
    # the linear scale, as before: the colour range from 0
    fig = show_ping_figure(p, scale="linear")
    assert fig.axes[0].images[0].get_clim()[0] == 0.0


@pytest.mark.parametrize("scale", ["db", "linear"])
def test_both_colour_bars_of_a_polar_figure_say_what_they_show(scale: str, data_dir: Path) -> None:
    from sonarmap.io import read_ping

    p = read_ping(data_dir / "kongsberg" / "0077_20221109_123655_Belgica.wcd", index=0)
    fig = show_ping_figure(p, polar=True, scale=scale)
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    want = "intensity (dB)" if scale == "db" else "intensity"
    assert [ax.get_ylabel() for ax in bars] == [want, want]


@pytest.mark.parametrize(("source", "name"), [
    ("/data/0077_20221109_123655_Belgica.all#head2031/ping59683",
     "0077_20221109_123655_Belgica.all#head2031/ping59683"),
    ("/tmp/oc_bag#/sonar/image:1", "oc_bag#/sonar/image:1"),
    ("/data/sample.aris#3", "sample.aris#3"),
])
def test_fan_title_names_the_file_and_the_ping_in_it(source: str, name: str) -> None:
    """Before: the title was the source's last path component, so a Kongsberg ping lost its
    file and head ('ping59681', the same for both heads) and a bag ping its file and topic
    ('image:1'). The title is the figure's: the Kongsberg name over the fan ran into the colour bar."""
    from sonarmap.geometry import preset
    from sonarmap.ping import Ping

    g = preset("didson-hf")
    ping = Ping(image=np.zeros(g.shape, np.float32), geometry=g, time_ns=0, source=source)
    fig = show_ping_figure(ping)
    title = fig.get_suptitle()
    assert title.split("\n")[0].split("  ")[0] == name and "1970-01-01T00:00:00.000 UTC" in title
    fig.canvas.draw()  # the whole title is on the figure, above the fan and its colour bar
    box = fig._suptitle.get_window_extent()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width
    assert box.y0 >= max(ax.get_window_extent().y1 for ax in fig.axes)


def test_fan_colour_bar_label_keeps_clear_of_the_polar_axis_label(data_dir: Path) -> None:
    """show --polar: the fan's colour-bar label and the polar panel's 'range (m)' were 10-11 px
    apart at 100 dpi; now at least 30 px (the report's figures have the same room)."""
    import io

    from sonarmap.io import read_ping

    for path in ("aris/sample.aris", "oculus/one_ping_8bit.raw"):
        fig = show_ping_figure(read_ping(data_dir / path, index=0), polar=True)
        fig.savefig(io.BytesIO(), format="png", dpi=100)
        r = fig._get_renderer()
        fan_bar, polar = fig.axes[2], fig.axes[1]
        assert polar.get_ylabel() == "range (m)"
        gap = polar.yaxis.label.get_window_extent(r).x0 - fan_bar.yaxis.label.get_window_extent(r).x1
        assert gap >= 30, (path, gap)


def test_bins_a_beam_did_not_record_are_drawn_as_no_data() -> None:
    """Before: the range bins past a Kongsberg water-column beam's last sample (filled with 0 by
    the reader) were drawn in the colour of the weakest echo (black, -84 dB) in the fan and the
    polar panel; now they are no data (grey), like the area outside the fan."""
    from sonarmap.geometry import preset
    from sonarmap.ping import Ping

    g = preset("didson-hf")
    n_bins, n_beams = g.shape
    count = np.full(n_beams, n_bins // 2)  # every beam recorded the nearer half of the window
    ping = Ping(image=np.full(g.shape, 0.5, np.float32), geometry=g, time_ns=0, source="em.all#head1/ping1",
                meta={"beam_start_sample": np.zeros(n_beams, int), "beam_n_samples": count})
    fig = show_ping_figure(ping, polar=True)
    polar = fig.axes[1].images[0].get_array()
    assert polar.mask[n_bins // 2:].all() and not polar.mask[: n_bins // 2].any()
    fan = fig.axes[0].images[0].get_array()
    x0, x1 = fig.axes[0].images[0].get_extent()[2:]
    x = np.linspace(x0, x1, fan.shape[0])
    far = x > g.range_m[n_bins // 2] + 0.1
    assert fan.mask[far].all() and (~fan.mask[x < g.range_m[n_bins // 2] - 0.1]).any()
    plain = show_ping_figure(Ping(image=np.full(g.shape, 0.5, np.float32), geometry=g, time_ns=0), polar=True)
    assert not np.ma.getmaskarray(plain.axes[1].images[0].get_array()).any()
