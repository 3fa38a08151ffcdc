"""Command-line interface: ``sonarmap <command>``.

Each sub-command lives in its own module ``sonarmap.cli.<name>`` exposing ``register(app)``; the
modules listed in :data:`COMMAND_MODULES` that exist are registered in that order.  Heavy imports
happen inside the command functions so ``sonarmap --help`` stays fast.

Exit codes: 0 success, 1 processing error (one line on stderr naming the file/argument and what is
wrong), 2 usage error.  ``--debug`` shows tracebacks.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
import logging
import os
import sys
import typing
import warnings
from collections.abc import Iterator

import typer
import typer.core

from sonarmap import __version__
from sonarmap.errors import SonarmapError, show_warning_one_line

__all__ = ["app", "main", "COMMAND_MODULES", "reflow_help", "state"]

COMMAND_MODULES = (
    "info",
    "show",
    "simulate",
    "calibrate",
    "preprocess",
    "fit",
    "paper",
    "segment",
    "ranges",
    "map",
    "convert",
    "process",
    "live",
    "report",
    "demo",
)

app = typer.Typer(
    name="sonarmap",
    help="Multibeam imaging-sonar processing: clean images, labels, ranges and maps.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)

state: dict[str, bool] = {"debug": False}


def _version(value: bool) -> None:
    if value:
        typer.echo(f"sonarmap {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show full tracebacks on errors."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """sonarmap: multibeam imaging-sonar processing."""
    state["debug"] = debug


def _plain_type(param: object) -> str | None:
    """Click-style type label of a parameter for ``--help``: ``PATH``, ``TEXT``, ``INTEGER``, ...

    Flags have none; an explicit ``metavar`` wins.  Replaces typer's annotation labels
    (``<bool>``, ``<list[Path]>``), which show Python types rather than what to type.
    """
    if getattr(param, "is_flag", False) or getattr(param, "count", False):
        return None
    metavar = getattr(param, "metavar", None)
    if metavar is not None and not isinstance(param, typer.core.TyperArgument):
        return str(metavar)
    desc = getattr(param, "type_descriptor", None)
    choices = getattr(desc, "choices", None) if getattr(desc, "is_choice", False) else None
    if choices:
        return "[" + "|".join(str(getattr(c, "value", c)) for c in choices) + "]"
    annotation = getattr(desc, "annotation", None)
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (list, tuple) and args:
        annotation = args[0]
    if isinstance(annotation, type) and issubclass(annotation, os.PathLike):
        return "PATH"
    return _TYPE_LABELS.get(annotation, "TEXT")  # type: ignore[arg-type]


#: Help labels of the annotation types the commands use.
_TYPE_LABELS: dict[type, str] = {int: "INTEGER", float: "FLOAT", str: "TEXT", bool: "BOOLEAN"}


def _usage_name(param: object) -> str:
    """An argument in the usage line: ``PINGS...`` (required) or ``[PINGS]...`` (optional)."""
    name = str(getattr(param, "metavar", None) or getattr(param, "name", "") or "").upper()
    if not getattr(param, "required", False):
        name = f"[{name}]"
    return name + ("..." if getattr(param, "nargs", 1) != 1 else "")


def _install_plain_help_types() -> None:
    """Make typer's help show click-style types (``PATH``) instead of ``<Path>``/``<bool>``."""
    core = typer.core
    for cls_name in ("TyperOption", "TyperArgument"):
        cls = getattr(core, cls_name, None)
        if cls is not None and hasattr(cls, "display_type_rich"):
            cls.display_type_rich = lambda self, ctx: _plain_type(self)  # type: ignore[method-assign]
    arg_cls = getattr(core, "TyperArgument", None)
    if arg_cls is not None and hasattr(arg_cls, "_usage_display_name"):
        arg_cls._usage_display_name = _usage_name  # type: ignore[method-assign]


def _fold_long_words() -> None:
    """Make the help text of options and arguments fold a word wider than its column.

    rich cuts such a word with an ellipsis (``time_ns|time_s,x,y,z,q…`` at 80 columns), hiding
    the end of the help; folded, it goes on at the start of the next line.  typer's help module is
    imported only when help is shown, so this is called from :func:`_install_folding_help`'s hook.
    """
    import typer.rich_utils as rich_utils

    make = rich_utils._make_rich_text
    if getattr(make, "_sonarmap_folds", False):
        return

    def folding(**kwargs: typing.Any) -> typing.Any:
        text = make(**kwargs)
        if hasattr(text, "overflow"):  # rich Text (not Markdown)
            text.overflow = "fold"
        return text

    folding._sonarmap_folds = True  # type: ignore[attr-defined]
    rich_utils._make_rich_text = folding  # type: ignore[assignment]


def _install_folding_help() -> None:
    """Fold long words in every command's ``--help`` (:func:`_fold_long_words`), without importing
    typer's help module (and rich) for commands that show no help."""
    for cls_name in ("TyperCommand", "TyperGroup"):
        cls = getattr(typer.core, cls_name, None)
        if cls is None or not hasattr(cls, "format_help"):
            continue
        original = cls.format_help

        def format_help(self: typing.Any, ctx: typing.Any, formatter: typing.Any,
                        _original: typing.Any = original) -> typing.Any:
            _fold_long_words()
            return _original(self, ctx, formatter)

        cls.format_help = format_help  # type: ignore[method-assign]


def reflow_help(text: str) -> str:
    r"""A command's docstring as ``--help`` text: each paragraph one line, for the terminal to wrap.

    typer keeps the single line breaks of a docstring's later paragraphs, so source lines wider
    than the terminal came out broken in two (a long line and a stub).  A paragraph whose first
    line is ``\b`` keeps its line breaks (the click convention; the marker itself is dropped).

    Examples
    --------
    >>> reflow_help("Title.\n\n    One sentence\n    over two lines.\n")
    'Title.\n\nOne sentence over two lines.'
    """
    paragraphs = inspect.cleandoc(text).split("\n\n")
    out = []
    for para in paragraphs:
        lines = para.split("\n")
        if lines[0].strip() == "\b":
            out.append("\n".join(lines[1:]))
        else:
            out.append(" ".join(line.strip() for line in lines if line.strip()))
    return "\n\n".join(out)


def _register_all() -> None:
    for name in COMMAND_MODULES:
        modname = f"sonarmap.cli.{name}"
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name == modname:
                continue
            raise
        mod.register(app)
    for info in app.registered_commands:
        doc = info.help if info.help is not None else (info.callback.__doc__ if info.callback else None)
        if doc:
            info.help = reflow_help(doc)


_install_plain_help_types()
_install_folding_help()
_register_all()


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


#: Loggers of libraries that print multi-line tracebacks on connection loss (a killed dask
#: scheduler or worker); the CLI reports such failures itself, in one line.
_QUIET_LOGGERS = ("distributed", "tornado", "asyncio")


def quiet_library_loggers() -> None:
    """Silence the loggers of dask.distributed and tornado (call after importing distributed).

    ``distributed`` configures its loggers when it is imported, so the CLI calls this again once
    a command has imported it; a lost scheduler is then reported by the command in one line.
    """
    if state.get("debug"):
        return
    names = [n for n in logging.root.manager.loggerDict if n.split(".", 1)[0] in _QUIET_LOGGERS]
    for name in {*names, *_QUIET_LOGGERS}:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


#: The warnings of the running command that a file's last frame/record was cut off and skipped
#: (a :class:`~sonarmap.io.PartialFrameWarning` ending ``; skipped``), held back by :func:`_show_warning`.
_held: list[str] = []


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: object | None = None, line: str | None = None) -> None:
    """:func:`~sonarmap.errors.show_warning_one_line`, except that a cut-off last frame is held
    back (once per file): printed when the command ends, or - if it ends with an error, typically
    "no complete ping" - told on the error's line (:func:`_with_held`), one line in all."""
    text = " ".join(str(message).split())
    io = sys.modules.get("sonarmap.io")  # not loaded: no such warning was raised
    if io is not None and issubclass(category, io.PartialFrameWarning) and text.endswith("; skipped"):
        if _same_file_key(text) not in [_same_file_key(t) for t in _held]:  # a file is often opened twice
            _held.append(text)
        return
    show_warning_one_line(message, category, filename, lineno, file, line)


def _same_file_key(text: str) -> str:
    """A ``<path>: at byte ...`` message with its path made absolute (the same file named two ways)."""
    path, sep, rest = text.partition(": at byte ")
    return os.path.abspath(path) + sep + rest if sep else text


def _with_held(msg: str) -> str:
    """The error message ``msg`` followed by the held cut-off-frame warnings (then forgotten)."""
    notes = [t.removesuffix("; skipped") + ", skipped" for t in _held]
    _held.clear()
    return "; ".join([msg, *notes])


@contextlib.contextmanager
def _cli_output(debug: bool) -> Iterator[None]:
    """One-line warnings and quiet library loggers for the duration of one CLI call."""
    saved_show = warnings.showwarning
    saved_levels = {name: logging.getLogger(name).level for name in _QUIET_LOGGERS}
    _held.clear()
    if not debug:
        warnings.showwarning = _show_warning
        for name in _QUIET_LOGGERS:
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        from sonarmap.errors import SonarmapWarning

        for text in _held:
            show_warning_one_line(text, SonarmapWarning, "", 0)
        _held.clear()
        warnings.showwarning = saved_show
        for name, level in saved_levels.items():
            logging.getLogger(name).setLevel(level)


def _is_dask_error(exc: BaseException) -> bool:
    mod = type(exc).__module__ or ""
    return mod.split(".", 1)[0] in {"distributed", "dask", "tornado"}


def main(argv: list[str] | None = None) -> int:
    """Console-script entry point; returns the exit code."""
    args = sys.argv[1:] if argv is None else argv
    debug = "--debug" in args
    with _cli_output(debug):
        return _main(args, debug)


def _main(args: list[str], debug: bool) -> int:
    try:
        rv = app(args=args, prog_name="sonarmap", standalone_mode=False)
        # typer turns Ctrl-C into Exit(130), *returned* (not raised) when standalone_mode=False.
        if isinstance(rv, int) and not isinstance(rv, bool) and rv != 0:
            if rv == 130:
                print("sonarmap: interrupted", file=sys.stderr)
            return rv
    except SystemExit as exc:  # pragma: no cover - typer.Exit inside standalone_mode=False
        code = exc.code
        return int(code) if isinstance(code, int) else (0 if code is None else 1)
    except KeyboardInterrupt:
        print("sonarmap: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the CLI boundary
        # typer vendors click, so match its exceptions by the public typer names / duck typing.
        if isinstance(exc, typer.Exit):
            return int(exc.exit_code)
        if isinstance(exc, typer.Abort):
            print("sonarmap: aborted", file=sys.stderr)
            return 1
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):  # click ClickException/UsageError
            exc.show()
            return int(exc.exit_code)
        if debug:
            raise
        if isinstance(exc, SonarmapError | OSError | ValueError):
            msg = _with_held(_one_line(exc) or type(exc).__name__)
            print(f"sonarmap: error: {msg}", file=sys.stderr)
            return 1
        if _is_dask_error(exc):
            msg = _one_line(exc) or "connection lost"
            print(f"sonarmap: error: dask: {type(exc).__name__}: {msg}", file=sys.stderr)
            return 1
        print(f"sonarmap: internal error: {type(exc).__name__}: {_one_line(exc)} (rerun with --debug)", file=sys.stderr)
        return 1
    return 0


def run() -> None:  # pragma: no cover - console script
    from sonarmap._threads import limit_blas_threads

    limit_blas_threads()  # small per-ping products: one BLAS thread (see sonarmap._threads)
    sys.exit(main())
