"""``sonarmap calibrate BACKGROUND... -o sonar.json``: taper, range gain and eq.-19 background model."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, OUTPUT_OPTION, load_geometry_option


def register(app: typer.Typer) -> None:
    """Add the ``calibrate`` command to ``app``."""

    @app.command("calibrate")
    def calibrate_cmd(
        background: list[Path] = typer.Argument(..., help="Open-water ping files, directories or globs."),
        output: Path = OUTPUT_OPTION,
        sonar: str | None = GEOMETRY_OPTION,
        method: str = typer.Option("lsq", "--method", "-m", help="Background fit: lsq (paper) or em."),
        taper_estimator: str = typer.Option(
            "mean",
            "--taper-estimator",
            help="Taper/range-gain estimator: 'mean' (per-beam pixel mean; reproduces the DIDSON "
            "files' taper, r=0.996) or 'nonzero-mean' (unbiased under a single receiver threshold, "
            "as in the simulator). See docs/preprocessing.md.",
        ),
    ) -> None:
        """Estimate taper, radial gain and p(y|B) = (1-pi_B) delta + pi_B lambda e^(-lambda y) (eq. 19).

        The geometry JSON written keeps every geometry field (taper replaced by the estimate) and adds
        ``calibration`` (ignored by load_geometry): background pi_B, lambda, KLD, the radial gain
        k1/k2/k3 and the pre-processing recipe used for the background statistics.
        """
        import json

        import numpy as np

        from sonarmap._atomic import atomic_write_text
        from sonarmap.errors import GeometryError, InputError
        from sonarmap.io import read_pings
        from sonarmap.paper import background_config
        from sonarmap.preprocess.gain import estimate_radial_gain, estimate_taper
        from sonarmap.preprocess.pipeline import preprocess_image
        from sonarmap.stats.mixture import fit_mixture, histogram

        geom_override = load_geometry_option(sonar)
        cfg = background_config()
        pings = list(read_pings([str(p) for p in background], geometry=geom_override))
        if not pings:
            raise InputError("background: no pings")
        geom = pings[0].geometry
        for p in pings[1:]:
            if p.geometry.shape != geom.shape or not np.allclose(p.geometry.azimuth_rad, geom.azimuth_rad):
                raise GeometryError(f"{p.source}: geometry differs from {pings[0].source} (mixed set)")
        counts = np.zeros(256)
        for p in pings:
            counts += histogram(preprocess_image(p.image, p.geometry, cfg), 256, binning="floor")
        fit = fit_mixture(counts, families=("exponential",), method=method, binning="floor")  # type: ignore[arg-type]
        if taper_estimator not in ("mean", "nonzero-mean"):
            raise typer.BadParameter("must be 'mean' or 'nonzero-mean'", param_hint="--taper-estimator")
        taper = estimate_taper(pings, estimator=taper_estimator)
        gain = estimate_radial_gain(pings, geom, estimator=taper_estimator)
        out_geom = geom.replace(taper=taper.taper)
        d = out_geom.to_dict()
        d["calibration"] = {
            "n_pings": len(pings),
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
        }
        atomic_write_text(output, json.dumps(d, indent=1) + "\n")
        typer.echo(
            f"pi_B={fit.weights[1]:.4f} lambda={1 / fit.params[1][0]:.2f} KLD={fit.kld:.3g} "
            f"({len(pings)} pings) -> {output}"
        )
