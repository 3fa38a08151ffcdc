"""``sonarmap ranges PING... -o ranges.csv``: per-beam first returns of structure.

Writes exactly one row per (ping, beam) with the header
``ping,beam,azimuth_rad,bin,range_m,intensity,flags,sigma_m,p_detect,time,time_ns``
(:data:`sonarmap.ranges.csv_rows.CSV_HEADER`, written by :func:`sonarmap.ranges.csv_rows.write_ranges_rows`;
an empty cell is "none" / "unknown", never a number that looks like one).
``-o -`` streams the CSV to stdout (the summary lines stay on stderr).

* ``ping``: the ping's source file path (and frame);
* ``beam``: 0-based beam (image column) index;
* ``azimuth_rad``: the beam's azimuth, radians, positive to starboard;
* ``bin``: 0-based range bin of the return (the bin at or after ``range_m``); empty where the
  beam has no return;
* ``range_m``: range of the return in metres, the leading edge of its echo: the first crossing
  of half the echo's peak along the beam, interpolated between bins (sub-bin), measured on the
  edge-aligned mean profile of up to 3 beams on either side on the same surface (the echo's
  peak with ``range_mode = "strongest"``); empty where the beam has no return;
* ``intensity``: the echo's strength, the image intensity at its first peak; empty where the beam has no return;
* ``flags``: the ping's fit gates, ``;``-separated, empty when the ping's fit is plausible;
* ``sigma_m``: one-sigma uncertainty of ``range_m`` in metres; empty where the beam has no
  return or no estimate;
* ``p_detect``: probability that a surface in this beam is detected and reported as its
  return (the occupancy map's per-beam pD), in [0, 1]; empty where unknown.  A property of the
  beam, so it may be set on a beam without a return;
* ``time``: the ping's time, ISO 8601 UTC to the nanosecond (``2016-07-19T14:03:05.250000000Z``;
  ``pandas.read_csv(path, parse_dates=["time"])`` gives ``datetime64[ns, UTC]``);
* ``time_ns``: the same time as integer nanoseconds since the Unix epoch (``Ping.time_ns``).

One summary line on stderr counts the flagged pings and their reasons;
``--strict`` exits 1 when any ping was flagged.  Without ``--method`` the
default :class:`sonarmap.pipeline.PipelineConfig` runs end to end (pre-processing, mixture fit,
exact graph-cut MRF, consistency-filtered first returns).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    PING_RATE_OPTION, START_TIME_OPTION, clock_options,
    CALIBRATION_OPTION, GEOMETRY_OPTION, OUTPUT_OPTION, PINGS_ARGUMENT, QUIET_OPTION, STDOUT, VERBOSE_OPTION, check_choice,
    apply_calibration, err_console, example, input_progress, load_geometry_option, open_output, output_name,
    read_input_pings,
)

__all__ = [
    "register", "pipeline_config_from_options", "flagged_summary", "flagged_any",
]

METHOD_OPTION: Any = typer.Option(
    None, "--method", "-m",
    help="Classifier: mrf (default pipeline), map, threshold, cfar-ca, cfar-so, cfar-go, cfar-os.",
)
SOLVER_OPTION: Any = typer.Option(None, "--solver", help="MRF solver: graphcut (exact, default), icm, anneal, expansion.")
BETA_OPTION: Any = typer.Option(None, "--beta", help="Potts weight of the MRF (eq. 22).")
STRICT_OPTION: Any = typer.Option(False, "--strict", help="Exit 1 when the model could not explain some ping (a flagged fit).")
CONFIG_OPTION: Any = typer.Option(None, "--config", "-c", help="Pipeline configuration TOML: a \\[pipeline] table and its stage tables (\\[pipeline.fit], \\[pipeline.classify], \\[pipeline.candidates], \\[pipeline.ranges]).")
_TO_OPTION: Any = typer.Option(
    None, "--to", help="Output kind: csv, bag1 (ROS 1 .bag) or bag2 (ROS 2 bag directory) of "
    "marine_acoustic_msgs/SonarRanges (default: bag1 for *.bag, else csv)."
)

if TYPE_CHECKING:
    from sonarmap.ping import Ping
    from sonarmap.pipeline import PingProducts


def pipeline_config_from_options(
    config: Path | None, method: str | None, solver: str | None, beta: float | None
) -> Any:
    """Build the PipelineConfig from ``--config`` and the override options.

    Parameters
    ----------
    config : Path, optional
        Pipeline configuration TOML (a bad file is a processing error, exit 1).
    method, solver : str, optional
        ``--method`` / ``--solver``; an unknown name is a usage error (exit 2).
    beta : float, optional
        ``--beta``; an invalid value is a usage error (exit 2).

    Returns
    -------
    PipelineConfig

    Raises
    ------
    typer.BadParameter
        If an option value is invalid (checked before ``config`` is read), or ``--solver`` /
        ``--beta`` is given for a method other than the MRF.
    """
    from sonarmap.errors import SonarmapError
    from sonarmap.pipeline import METHODS, SOLVER_NAMES, PipelineConfig

    changes: dict[str, Any] = {}
    if method is not None:
        changes["method"] = check_choice(method, METHODS, "--method")
    if solver is not None:
        changes["solver"] = check_choice(solver, SOLVER_NAMES, "--solver")
    if beta is not None:
        try:
            PipelineConfig().replace(beta=beta)
        except (SonarmapError, ValueError) as exc:
            raise typer.BadParameter(str(exc), param_hint="--beta") from None
        changes["beta"] = beta
    cfg = PipelineConfig.from_toml(config) if config is not None else PipelineConfig()
    cfg = cfg.replace(**changes) if changes else cfg
    for option, value in (("--solver", solver), ("--beta", beta)):
        if value is not None and cfg.classify.method != "mrf":  # the MRF's options; no other method reads them
            raise typer.BadParameter(f"applies to the MRF only; the method is {cfg.classify.method} (give --method mrf)",
                                     param_hint=option)
    return cfg


def flagged_summary(gates: list[tuple[str, ...]]) -> str:
    """One line: ``"2 of 6 pings flagged: kld (2)"``, plus the pings without an object class.

    Flagged pings fail a gate of :data:`sonarmap.stats.gates.IMPLAUSIBLE`; ``collapsed`` pings
    (explained by the background alone) are counted after a semicolon.
    """
    from collections import Counter

    from sonarmap.stats.gates import IMPLAUSIBLE

    bad = [tuple(g for g in gs if g in IMPLAUSIBLE) for gs in gates]
    n = sum(1 for g in bad if g)
    line = f"{n} of {counted(len(gates), 'ping')} flagged"
    if n:
        counts = Counter(name for g in bad for name in g)
        line += ": " + ", ".join(f"{k} ({v})" for k, v in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))
    n_bg = sum(1 for gs, b in zip(gates, bad) if "collapsed" in gs and not b)
    if n_bg:
        line += f"; {n_bg} explained by the background alone (collapsed: no returns)"
    return line


def flagged_any(gates: list[tuple[str, ...]]) -> bool:
    """Whether any ping failed a gate of :data:`sonarmap.stats.gates.IMPLAUSIBLE` (``--strict``)."""
    from sonarmap.stats.gates import IMPLAUSIBLE

    return any(set(g) & IMPLAUSIBLE for g in gates)


def register(app: typer.Typer) -> None:
    """Add the ``ranges`` command to ``app``."""

    @app.command("ranges", epilog=example("ranges pings/ -o ranges.csv", "ranges recording.aris -o - --method threshold"))
    def ranges_cmd(
        pings: list[Path] = PINGS_ARGUMENT,
        output: Path = OUTPUT_OPTION,
        sonar: str | None = GEOMETRY_OPTION,
        start_time: str | None = START_TIME_OPTION,
        ping_rate: float | None = PING_RATE_OPTION,
        method: str | None = METHOD_OPTION,
        solver: str | None = SOLVER_OPTION,
        beta: float | None = BETA_OPTION,
        config: Path | None = CONFIG_OPTION,
        strict: bool = STRICT_OPTION,
        calibration: Path | None = CALIBRATION_OPTION,
        to: str | None = _TO_OPTION,
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Per-beam first-return ranges of structure, one CSV row per (ping, beam).

        Columns (an empty cell: no return, no estimate or unknown):
        ping: source file; beam: 0-based beam index; azimuth_rad: beam azimuth;
        bin: 0-based range bin of the return;
        range_m: echo's leading edge (first crossing of half its peak, sub-bin, on the
        edge-aligned mean of up to 7 neighbouring beams of the same surface);
        intensity: the echo's strength (image intensity at its first peak); flags: the ping's fit gates;
        sigma_m: one-sigma uncertainty of range_m (m);
        p_detect: probability that a surface in the beam is detected and reported;
        time: ping time, ISO 8601 UTC with ns; time_ns: ping time, integer ns since the epoch.

        Give -o - to write the CSV to stdout (the summary stays on stderr).  The CSV file is
        replaced atomically when the command succeeds.  -o x.bag (or --to bag1/bag2) writes
        one marine_acoustic_msgs/SonarRanges message per ping instead (docs/formats.md).
        """
        import contextlib
        import csv

        from sonarmap.pipeline import process_ping

        out_kind = _output_kind(to, output)
        bag_items: list[tuple[Any, Any]] = []
        cfg = pipeline_config_from_options(config, method, solver, beta)
        geom = load_geometry_option(sonar)
        clock = clock_options(start_time, ping_rate)
        cfg, rec = apply_calibration(cfg, calibration)
        n_pings = n_rows = n_ret = 0
        gated: list[tuple[str, ...]] = []
        bar = input_progress("ranges", pings, quiet=quiet, verbose=verbose, compiles=True)
        out_cm: Any = contextlib.nullcontext(None) if out_kind != "csv" else open_output(output, newline="")
        with out_cm as fh, bar:
            w = csv.writer(fh) if fh is not None else None
            # before the bar: an unreadable input prints only its error
            ping_iter = read_input_pings(pings, geom, clock=clock)
            bar.start()
            for ping in ping_iter:
                prod = process_ping(ping, cfg, background=rec)
                n_rows += _record_ranges(w, bag_items, ping, prod, first=n_pings == 0)
                n_ret += prod.ranges.n_returns
                n_pings += 1
                gated.append(prod.gates)
                bar.advance()
                bar.log(f"{ping.source}: {prod.ranges.n_returns} returns"
                        + (f" ({';'.join(prod.gates)})" if prod.gates else ""))
        if out_kind != "csv":
            from sonarmap.io.rosbag_products import write_ranges_bag

            write_ranges_bag(bag_items, output, version=1 if out_kind == "bag1" else 2)
        if not quiet:
            _print_summary(n_pings, n_rows, n_ret, output_name(output), cfg, gated)
        if strict and flagged_any(gated):
            raise typer.Exit(1)


def _output_kind(to: str | None, output: Path) -> str:
    """``csv``, ``bag1`` or ``bag2``: ``--to``, else from the suffix of ``-o``; a usage error for an
    unknown kind or a bag to stdout."""
    if to is not None:
        check_choice(to, ("csv", "bag1", "bag2"), "--to")
    out_kind = to or ("bag1" if output.suffix == ".bag" else "csv")
    if out_kind != "csv" and str(output) == STDOUT:
        raise typer.BadParameter("a bag cannot be written to stdout; give a path", param_hint="--output")
    return out_kind


def _record_ranges(w: Any, bag_items: list[tuple[Any, Any]], ping: Ping, prod: PingProducts, *, first: bool) -> int:
    """Write one ping's ranges as CSV rows with the writer ``w`` (the header before the first ping's rows),
    or without a writer (``w`` None) keep them for the bag in ``bag_items``; returns the number of rows."""
    if w is None:
        bag_items.append((ping.geometry, prod.ranges))
        return prod.ranges.n_beams
    from sonarmap.ranges.csv_rows import CSV_HEADER, write_ranges_rows

    if first:
        w.writerow(CSV_HEADER)  # after the first ping: an unreadable input writes nothing
    return write_ranges_rows(w, ping.source, prod.ranges, ";".join(prod.gates), time_ns=ping.time_ns)


def _print_summary(n_pings: int, n_rows: int, n_ret: int, where: str, cfg: Any,
                   gated: list[tuple[str, ...]]) -> None:
    """The two summary lines of ``ranges`` on stderr."""
    console = err_console()
    console.print(
        f"{counted(n_pings, 'ping')}, {counted(n_rows, 'row')} ({counted(n_ret, 'return')}) -> {where} (method={cfg.classify.method}"
        + (f", solver={cfg.classify.solver}" if cfg.classify.method == "mrf" else "") + ")", markup=False
    )
    console.print(flagged_summary(gated), markup=False)
