"""``sonarmap paper --data DIDSON -o OUT/``: reproduce Table I, the background model, Figs. 2/3/5/6/8."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import OUTPUT_DIR_OPTION, QUIET_OPTION, example


def register(app: typer.Typer) -> None:
    """Add the ``paper`` command to ``app``."""

    @app.command("paper", epilog=example("paper --data /data/didson -o paper-out/"))
    def paper_cmd(
        data: Path = typer.Option(..., "--data", help="The DIDSON folder (with test/ and background/)."),
        output: Path = OUTPUT_DIR_OPTION,
        quiet: bool = QUIET_OPTION,
    ) -> None:
        """Write table1.csv, background.csv, fig2, fig3, fig5, fig6 and fig8 (PNG), and print Table I.

        Fig. 2 is the sonar model (beam pattern, Wiener filter, taper), Fig. 3 the pre-processing of
        a hull ping and the channel model, Fig. 5 the background histograms, Fig. 6 the ROC curves,
        Fig. 8 the per-image mixture fits (docs/statistics.md says what each panel shows).

        Table I (this implementation, the paper's values and EM) is the result, on stdout; the
        output directory is created if needed and its files are replaced.
        """
        if not data.is_dir():
            raise typer.BadParameter(f"{data}: not a directory (the DIDSON folder with test/ and background/)",
                                     param_hint="--data")
        import contextlib

        from sonarmap.cli._common import err_console
        from sonarmap.paper import PAPER_BACKGROUND, PAPER_OUTPUTS, PAPER_TABLE1, Table1Row, write_paper_outputs

        # a spinner on a terminal (the library reports no per-ping progress); nothing on a pipe
        status = contextlib.nullcontext() if quiet else err_console().status("paper: Table I, background, figures")
        with status:
            res = write_paper_outputs(data, output)
        typer.echo("image   pi1    lambda    pi2    sigma   KLDe-3 | paper: pi1 lambda pi2 sigma KLDe-3 | EM: pi1 lambda pi2 sigma KLDe-3  flags")
        for r in res["rows"]:
            o = Table1Row.cells(r.paper)
            e = Table1Row.cells(r.em)
            p = PAPER_TABLE1[r.image]
            typer.echo(
                f"{r.image:5d} {o[0]:.3f} {o[1]:8.3f} {o[2]:.3f} {o[3]:.3f} {o[4] * 1e3:7.3f} | "
                f"{p[0]:.3f} {p[1]:7.3f} {p[2]:.3f} {p[3]:.3f} {p[4] * 1e3:6.3f} | "
                f"{e[0]:.3f} {e[1]:7.3f} {e[2]:.3f} {e[3]:.3f} {e[4] * 1e3:6.3f}  "
                f"{','.join(sorted(r.paper.flags)) or '-'} {'ok' if all(r.within_tolerance()) else 'OUT'}"
            )
        b = res["background"]
        typer.echo(f"background: pi_B={b.weights[1]:.4f} lambda={1 / b.params[1][0]:.2f} KLD={b.kld:.3g} "
                   f"(paper {PAPER_BACKGROUND[0]}, {PAPER_BACKGROUND[1]}, {PAPER_BACKGROUND[2]:.3g})")
        if not quiet:
            typer.echo(f"wrote {output}/{', '.join(PAPER_OUTPUTS)}", err=True)
