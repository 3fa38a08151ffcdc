"""``sonarmap calibrate RECORDING... -o sonar.json``: background level, taper, range gain and model.

Two kinds of recording:

* **thresholded** (the pings' median zero fraction >= 0.2: DIDSON): an open-water set gives the
  paper's calibration - per-beam taper, radial gain ``k(r)`` (eq. 7) and the eq.-19 background
  ``p(y|B) = (1-pi_B) delta + pi_B lambda e^(-lambda y)`` - written into the geometry JSON;
* **any other recording** (ARIS, Oculus, water column; targets may be present): the background
  level against range and beam (the median over the pings of each ping's estimate,
  :mod:`sonarmap.preprocess.normalise`), its net range dependence fitted with the channel model of
  eq. 6-7, the per-beam taper it implies, and the intensity model chosen on the pooled normalised
  pings; ``sonarmap ranges --calibration sonar.json`` then normalises every ping by the recording's
  level instead of its own.

Either way the output says what the data could not support.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    PING_RATE_OPTION, START_TIME_OPTION, clock_options,
    GEOMETRY_OPTION, OUTPUT_OPTION, QUIET_OPTION, VERBOSE_OPTION, check_choice, err_console, example,
    input_progress, load_geometry_option, open_output, output_name, read_input_pings,
)


def register(app: typer.Typer) -> None:
    """Add the ``calibrate`` command to ``app``."""

    @app.command("calibrate", epilog=example("calibrate background/ -o sonar.json",
                                             "calibrate recording.aris -o - -q > sonar.json"))
    def calibrate_cmd(
        recording: list[Path] = typer.Argument(..., help="Recording(s): ping files, directories or globs (any format)."),
        output: Path = OUTPUT_OPTION,
        sonar: str | None = GEOMETRY_OPTION,
        start_time: str | None = START_TIME_OPTION,
        ping_rate: float | None = PING_RATE_OPTION,
        method: str = typer.Option("lsq", "--method", "-m", help="Background fit: lsq (paper) or em."),
        taper_estimator: str = typer.Option(
            "mean",
            "--taper-estimator",
            help="Taper/range-gain estimator: 'mean' (per-beam pixel mean; reproduces the DIDSON "
            "files' taper, r=0.996) or 'nonzero-mean' (unbiased under a single receiver threshold, "
            "as in the simulator). See docs/preprocessing.md.",
        ),
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Estimate the background of a recording: level vs range and beam, taper, range gain, model.

        Thresholded recordings (DIDSON open water): taper, radial gain and the eq.-19 background
        p(y|B) = (1-pi_B) delta + pi_B lambda e^(-lambda y), with the taper written into the
        geometry.  Any other recording: the background level vs range and beam, its range
        dependence (eq. 6-7), taper and the intensity model; pass the output to
        sonarmap ranges --calibration.  The geometry JSON gains a calibration table (ignored when
        the file is read as a geometry) that also lists what could not be estimated.  Give -o - to
        write the JSON to stdout (the summary then goes to stderr); a file is replaced atomically.
        """
        import json

        import numpy as np

        from sonarmap.errors import GeometryError
        from sonarmap.preprocess.normalise import estimate_recording_background

        check_choice(method, ("lsq", "em"), "--method")
        check_choice(taper_estimator, ("mean", "nonzero-mean"), "--taper-estimator")
        clock = clock_options(start_time, ping_rate)
        # before the bar
        ping_iter = read_input_pings(recording, load_geometry_option(sonar), "recording", "no pings", clock=clock)
        pings = []
        with input_progress("calibrate", recording, quiet=quiet, verbose=verbose) as bar:
            bar.start()
            for ping in ping_iter:
                pings.append(ping)
                bar.advance()
                bar.log(f"read {ping.source}")
            geom = pings[0].geometry
            for p in pings[1:]:
                if p.geometry.shape != geom.shape or not np.allclose(p.geometry.azimuth_rad, geom.azimuth_rad):
                    raise GeometryError(_mixed_geometry_message(p, pings[0]))
            rec = estimate_recording_background(pings)
            if rec.thresholded:
                d, lines = _calibrate_thresholded(pings, geom, method, taper_estimator)
            else:
                d, lines = _calibrate_normalised(pings, geom, rec)
            d["calibration"]["background_level"] = rec.to_dict()
            with open_output(output) as fh:
                fh.write(json.dumps(d, indent=1) + "\n")
        if quiet:
            return
        # the summary is a message: on stderr (the calibration itself is the file, or stdout)
        for line in [*lines, f"-> {output_name(output)}"]:
            err_console().print(line, markup=False, soft_wrap=True)


def _mixed_geometry_message(ping: Any, first: Any) -> str:
    """Why ``ping`` cannot be calibrated with ``first``: what differs, and what to do instead."""
    a, b = ping.geometry, first.geometry
    what = (f"{a.n_bins} bins x {a.n_beams} beams where {first.source} has {b.n_bins} x {b.n_beams}"
            if a.shape != b.shape else f"other beam azimuths than {first.source}")
    return (f"{ping.source}: {what}; calibrate needs the pings of one sonar setting (a recording whose "
            "range window or beams change every ping, such as Kongsberg water column, has no "
            "calibration: ranges and map normalise each ping by its own background)")


def _calibrate_thresholded(pings: list, geom: object, method: str, taper_estimator: str) -> tuple[dict, list[str]]:  # type: ignore[type-arg]
    """The paper's open-water calibration (eq. 5-7, 19) of a thresholded recording."""
    import numpy as np

    from sonarmap.paper import background_config
    from sonarmap.preprocess.gain import estimate_radial_gain, estimate_taper
    from sonarmap.preprocess.pipeline import preprocess_image
    from sonarmap.stats.mixture import fit_mixture, histogram

    cfg = background_config()
    counts = np.zeros(256)
    for p in pings:
        counts += histogram(preprocess_image(p.image, p.geometry, cfg), 256, binning="floor")
    fit = fit_mixture(counts, families=("exponential",), method=method, binning="floor")  # type: ignore[arg-type]
    taper = estimate_taper(pings, estimator=taper_estimator)  # type: ignore[arg-type]
    gain = estimate_radial_gain(pings, geom, estimator=taper_estimator)  # type: ignore[arg-type]
    out_geom = geom.replace(taper=taper.taper)  # type: ignore[attr-defined]
    d = out_geom.to_dict()
    not_estimated = []
    if len(pings) < 10:
        not_estimated.append(f"only {len(pings)} pings: taper and p(y|B) need an open-water set (tens of pings)")
    d["calibration"] = {
        "n_pings": len(pings),
        "kind": "thresholded",
        "background_model": "eq19: (1-pi_B) delta(y) + pi_B lambda exp(-lambda y)",
        "pi_B": float(fit.weights[1]),
        "lambda": float(1.0 / fit.params[1][0]),
        "kld": float(fit.kld),
        "fit_method": method,
        "flags": sorted(fit.flags),
        "histogram": "256 bins [k/256,(k+1)/256) on [0,1], pooled",
        "preprocess": cfg.to_dict(),
        "taper": taper.to_dict(),
        "radial_gain": gain.to_dict() if hasattr(gain, "to_dict") else repr(gain),
        "not_estimated": not_estimated,
    }
    lines = [f"pi_B={fit.weights[1]:.4f} lambda={1 / fit.params[1][0]:.2f} KLD={fit.kld:.3g} "
             f"({len(pings)} pings, thresholded: the paper's eq. 19 background)"]
    lines += [f"cannot estimate: {x}" for x in not_estimated]
    return d, lines


_CANDIDATES = (("exponential", "rayleigh"), ("gamma", "rayleigh"), ("weibull", "rayleigh"),
               ("exponential", "gamma"))


def _calibrate_normalised(pings: list, geom: object, rec: object) -> tuple[dict, list[str]]:  # type: ignore[type-arg]
    """Background level vs range and beam, channel fit, taper and model of any other recording."""
    import math

    import numpy as np

    from sonarmap.errors import FitError
    from sonarmap.preprocess.gain import fit_range_profile
    from sonarmap.preprocess.normalise import estimate_background
    from sonarmap.stats.mixture import histogram
    from sonarmap.stats.selection import select_model

    level = rec.level_by_bin  # type: ignore[attr-defined]
    r = np.asarray(geom.range_m, dtype=np.float64)  # type: ignore[attr-defined]
    not_estimated: list[str] = []
    # net range dependence of the background (after the sonar's own gain): eq. 6-7 regression
    gain_d = None
    try:
        gain_d = fit_range_profile(level, r, usable=r > 0, what="range bins beyond 0 m").to_dict()
    except FitError:
        pass
    if not r[0] > 0:
        not_estimated.append("the window starts at 0 m: the range fit uses the bins beyond it")
    if rec.range_dependence_db < 1.0:  # type: ignore[attr-defined]
        not_estimated.append("radial gain: the background is flat over the window (the sonar applied TVG); "
                             "none is applied")
    taper = rec.beam_profile()  # type: ignore[attr-defined]
    # intensity model on the pooled normalised pings
    counts = np.zeros(256)
    for p in pings:
        _, u = estimate_background(p.image, reference=rec)  # type: ignore[arg-type]
        if u is not None:
            counts += histogram(u, 256)
    model: dict[str, object] = {}
    try:
        sel = select_model(counts, candidates=_CANDIDATES, method="em")
        best = sel.best
        model = {"families": list(sel.candidates[sel.best_index]), "weights": [float(w) for w in best.weights],
                 "params": [list(p) for p in best.params], "kld": float(best.kld), "flags": sorted(best.flags),
                 "table": sel.table()}
    except FitError as exc:
        not_estimated.append(f"intensity model: {exc}")
    n = rec.n_pings  # type: ignore[attr-defined]
    if n < 10:
        not_estimated.append(
            f"only {counted(n, 'ping')}: the level is the median of {n} per-ping estimates, so a "
            "target that stays in the window still biases it where it is (10+ pings of a moving platform "
            "or of open water average it out)")
    if n == 1:
        not_estimated.append("ping-to-ping variability: one ping")
    not_estimated.append("absolute levels (source level, receiver gain): the file's counts are relative")
    d = geom.to_dict()  # type: ignore[attr-defined]
    d["calibration"] = {
        "n_pings": n,
        "kind": "normalised",
        "background_model": "level b(r) f(r, theta) from the data; normalised image = zero spike + exponential",
        "radial_gain": gain_d,
        "taper": [float(v) for v in taper],
        "model": model,
        "not_estimated": not_estimated,
    }
    fam = "+".join(model["families"]) if model else "none"  # type: ignore[arg-type]
    lines = [
        f"background: {counted(n, 'ping')}, not thresholded (zero fraction "
        f"{rec.zero_fraction:.3f}); level {float(level[0]):.3g} at {r[0]:.2f} m to "  # type: ignore[attr-defined]
        f"{float(level[-1]):.3g} at {r[-1]:.2f} m "
        f"({rec.range_dependence_db:.1f} dB between deciles"  # type: ignore[attr-defined]
        + (f", ping-to-ping {rec.ping_spread_db:.2f} dB" if math.isfinite(rec.ping_spread_db) else "")  # type: ignore[attr-defined]
        + ")",
        (f"range dependence: k1={gain_d['k1']:.2f} dB/decade, k2={gain_d['k2']:.3f} dB/m (rms {gain_d['rms_db']:.2f} dB)"
         if gain_d else "range dependence: too few range bins"),
        f"taper: {float(taper.min()):.2f}-{float(taper.max()):.2f} across {taper.size} beams",
        f"intensity model (normalised): {fam}",
    ]
    lines += [f"cannot estimate: {x}" for x in not_estimated]
    return d, lines
