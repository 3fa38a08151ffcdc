"""``sonarmap segment PING... -o DIR``: label images and a Fig.-7-style figure per ping.

For every ping writes ``<stem>_labels.png`` (8-bit, label value x 127: 0 background, 127 structure,
254 a second object class) and ``<stem>_segment.png``: raw | fixed threshold | MRF, like Fig. 7 of
Teixeira et al. (2018).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    PING_RATE_OPTION, START_TIME_OPTION, clock_options,
    CALIBRATION_OPTION, GEOMETRY_OPTION, OUTPUT_DIR_OPTION, PINGS_ARGUMENT, QUIET_OPTION, VERBOSE_OPTION,
    apply_calibration, err_console, example, input_progress, load_geometry_option, read_input_pings, run_pings,
)
from sonarmap.cli.ranges import BETA_OPTION, CONFIG_OPTION, METHOD_OPTION, SOLVER_OPTION, pipeline_config_from_options
from sonarmap.ping import source_file

__all__ = ["register", "segment_figure"]


#: The fixed threshold of the paper's Fig. 7 (its middle panel), on the pre-processed image.
FIG7_THRESHOLD = 0.22


def _stem(source: str, index: int) -> str:
    if not source:
        return f"ping{index:05d}"
    p = Path(source_file(source))
    stem = p.stem[:-4] if p.stem.endswith("_raw") else p.stem
    if "#" in source:
        stem += "_" + source.split("#", 1)[1]
    return stem


def segment_figure(raw: Any, threshold_labels: Any, labels: Any, ranges: Any, *, title: str = "",
                   threshold: float = FIG7_THRESHOLD, method: str = "mrf") -> Any:
    """Matplotlib figure: raw | fixed threshold | MRF labels with first returns overlaid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axs = plt.subplots(1, 3, figsize=(9, 6), sharey=True)
    axs[0].imshow(np.sqrt(np.clip(raw, 0, None)), cmap="gray", aspect="auto", interpolation="nearest")
    axs[0].set_title("raw")
    axs[1].imshow(threshold_labels, cmap="gray", aspect="auto", interpolation="nearest", vmin=0, vmax=1)
    n_px = int(np.count_nonzero(threshold_labels))
    # the paper's Fig. 7 threshold on the image the classifier saw: a threshold tuned on DIDSON can
    # select nothing on a normalised sonar (ARIS), and the panel must say so rather than look broken
    axs[1].set_title(f"fixed threshold {threshold:g}" + ("\n(no pixel reaches it)" if n_px == 0 else f"\n({n_px} px)"))
    axs[2].imshow(labels, cmap="gray", aspect="auto", interpolation="nearest", vmin=0, vmax=max(1, int(labels.max())))
    v = np.flatnonzero(ranges.valid)
    axs[2].plot(v, ranges.bin[v], ".", color="tab:red", ms=3, label="first return")
    axs[2].set_title(f"{method.upper()}\n({int(np.count_nonzero(labels))} px, {v.size} returns)")
    axs[2].legend(loc="lower right", fontsize=7)
    axs[0].set_ylabel("range bin")
    for ax in axs:
        ax.set_xlabel("beam")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def register(app: typer.Typer) -> None:
    """Add the ``segment`` command to ``app``."""

    @app.command("segment", epilog=example("segment pings/ -o labels/", "segment recording.aris -o labels/ --no-figure -q"))
    def segment_cmd(
        pings: list[Path] = PINGS_ARGUMENT,
        output: Path = OUTPUT_DIR_OPTION,
        sonar: str | None = GEOMETRY_OPTION,
        start_time: str | None = START_TIME_OPTION,
        ping_rate: float | None = PING_RATE_OPTION,
        method: str | None = METHOD_OPTION,
        solver: str | None = SOLVER_OPTION,
        beta: float | None = BETA_OPTION,
        config: Path | None = CONFIG_OPTION,
        calibration: Path | None = CALIBRATION_OPTION,
        figure: bool = typer.Option(True, "--figure/--no-figure", help="Write the raw | threshold | MRF figure."),
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Segment pings; write label images and Fig.-7-style figures.

        For every ping writes STEM_labels.png (0 background, 127 structure, 254 a second object
        class) and STEM_segment.png (raw | the fixed threshold 0.22 of the paper's Fig. 7 | the
        chosen method, first returns overlaid) into the output directory,
        which is created if needed; files in it are replaced atomically.

        STEM is the ping's file name, with its place in a recording after _ (sample_3); a Kongsberg
        ping's is FILE_headID/pingN, a folder per head.
        """
        from sonarmap._atomic import make_output_dir

        cfg, background = apply_calibration(pipeline_config_from_options(config, method, solver, beta), calibration)
        clock = clock_options(start_time, ping_rate)
        # before the bar and the directory
        ping_iter = read_input_pings(pings, load_geometry_option(sonar), clock=clock)
        make_output_dir(output)
        bar = input_progress("segment", pings, quiet=quiet, verbose=verbose, compiles=True)
        n = run_pings(bar, ping_iter, lambda ping, i: _segment_one(ping, i, output, cfg, figure, background))
        if not quiet:
            err_console().print(f"segmented {counted(n, 'ping')} -> {output}", markup=False)


def _segment_one(ping: Any, i: int, output: Path, cfg: Any, figure: bool, background: Any = None) -> str:
    """Segment one ping (normalised by the recording's ``background`` if given) and write its label
    image (and figure) into ``output``; returns the ``--verbose`` line."""
    import io

    import numpy as np
    from PIL import Image

    from sonarmap._atomic import atomic_path, atomic_write_bytes
    from sonarmap.classify.threshold import threshold_labels
    from sonarmap.ping import source_name
    from sonarmap.pipeline import process_ping

    prod = process_ping(ping, cfg, keep_labels=True, background=background)
    labels = prod.labels
    assert labels is not None
    stem = _stem(ping.source, i)
    buf = io.BytesIO()
    Image.fromarray((np.minimum(labels, 2) * 127).astype(np.uint8), mode="L").save(buf, format="PNG")
    atomic_write_bytes(output / f"{stem}_labels.png", buf.getvalue())
    if figure:
        import matplotlib.pyplot as plt

        # the fixed threshold of the paper's Fig. 7 on the image the classifier saw (pre-processed
        # or normalised); --method threshold uses its own (PipelineConfig.classify.threshold)
        img = prod.image if prod.image is not None else ping.image
        thr = threshold_labels(np.clip(img, 0.0, 1.0), FIG7_THRESHOLD)
        fig = segment_figure(ping.image, thr, labels, prod.ranges, title=source_name(ping.source),
                             threshold=FIG7_THRESHOLD, method=cfg.classify.method)
        with atomic_path(output / f"{stem}_segment.png") as tmp:
            fig.savefig(tmp, dpi=90, format="png")
        plt.close(fig)
    return f"{ping.source} -> {output / stem}_labels.png"
