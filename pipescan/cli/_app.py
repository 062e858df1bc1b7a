"""The ``pipescan`` app object, shared options and helpers of the command modules."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import signal
import sys
import threading
import traceback
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from typer.core import TyperGroup

try:  # typer 0.2x carries its own copy of click
    from typer._click import exceptions as click_errors
    from typer._click.utils import PacifyFlushWrapper
except ImportError:  # pragma: no cover - older typer, on click itself
    from click import exceptions as click_errors  # type: ignore[no-redef]
    from click.utils import PacifyFlushWrapper  # type: ignore[no-redef]

import pipescan
from pipescan.core.contour import CONTOUR_METHODS, DEFAULT_CONTOUR_METHOD
from pipescan.core.errors import OptionError, PipescanError

# Prefect reads its settings at import: set ours before any import of it.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "pipescan")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
# The CLI logs its own stage lines outside flow runs too; those are not for the API.
os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")
# A bad archive is one line ("error: ..."), exit code 2; Prefect's run loggers would print the
# same error again with a traceback. pipescan's logging file for Prefect keeps the run loggers
# off the terminal and sends their lines (a run's progress, its summary, its error) to the
# API, where the run's UI shows them; --verbose adds the terminal. A file the user set wins
# (PREFECT_LOGGING_SETTINGS_PATH, or Prefect's default place for it in PREFECT_HOME).
PREFECT_LOGGING_FILE = Path(__file__).with_name("prefect-logging.yml")
_USER_LOGGING_FILE = Path(os.environ.get("PREFECT_HOME", "~/.prefect")).expanduser() / "logging.yml"
if not _USER_LOGGING_FILE.is_file():
    os.environ.setdefault("PREFECT_LOGGING_SETTINGS_PATH", str(PREFECT_LOGGING_FILE))
_RUN_LOGGER_HANDLERS = (
    "PREFECT_LOGGING_LOGGERS_PREFECT_FLOW_RUNS_HANDLERS",
    "PREFECT_LOGGING_LOGGERS_PREFECT_TASK_RUNS_HANDLERS",
)
# Prefect waits 20 s for its temporary API server, which a busy machine (a network run's
# workers on all cores) can miss: the run would fail before it starts.
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")

_DEBUG = {"on": False}
"""Set by ``--debug``."""


def _debugging() -> bool:
    """``--debug`` or ``PIPESCAN_DEBUG=1``: expected errors show their traceback too."""
    env = os.environ.get("PIPESCAN_DEBUG", "").strip().lower()
    return _DEBUG["on"] or env in ("1", "true", "yes", "on")


def _error_line(text: str) -> None:
    typer.secho(f"error: {text}", fg=typer.colors.RED, err=True)


_INTERRUPTED = threading.Event()
"""Set by the first Ctrl-C (SIGINT) of a command."""

INTERRUPTED_EXIT_CODE = 130
"""What a shell reports for a command stopped by Ctrl-C (128 + SIGINT)."""

INTERRUPT_GRACE_S = 10.0
"""How long the first Ctrl-C lets the command unwind before it is stopped."""

_INTERRUPTED_LINE = (
    "error: interrupted: nothing more was stored (an inspection is stored whole or not at "
    "all; the next run removes this run's scratch files)\n"
)


def _on_interrupt(signum: int, frame: Any) -> None:
    """Ctrl-C. The first unwinds the command as Python does (a KeyboardInterrupt: files being
    written are removed, transactions rolled back) and stops it once that is done, or after
    :data:`INTERRUPT_GRACE_S`; a second stops it at once.

    In a terminal, Ctrl-C reaches the whole foreground process group, and Prefect's temporary
    API server stops with it. Prefect then tries to report the run's end to the stopped server
    for a minute or more (71.8 s measured on a 10 m scan, each failed attempt logged with its
    whole event), and its exit hooks wait for it for longer still (over 200 s): nothing of
    that can succeed, so Prefect's logging is silenced from the first Ctrl-C and the process
    does not wait for it. Stopping is safe: the database commits an inspection whole or not
    at all, the engine pool's workers exit with their parent, and the next run removes the
    scratch directory (``pipescan.flows.housekeeping``).
    """
    if _INTERRUPTED.is_set():
        _stop_now(_INTERRUPTED_LINE.replace("interrupted:", "interrupted again: stopped at once;"))
    _INTERRUPTED.set()
    # What Prefect says from here on (failed logs and events, each with its payload) is
    # about its stopped server; pipescan's own lines go straight to the terminal (fd 2).
    logging.disable(logging.CRITICAL)
    for logger in list(logging.root.manager.loggerDict.values()):
        if isinstance(logger, logging.Logger):  # Prefect's own ignore logging.disable
            logger.disabled = True
    sys.stderr = open(os.devnull, "w")  # noqa: SIM115  (for the rest of the process)
    os.write(2, b"interrupted: stopping (Ctrl-C again to stop at once)\n")
    timer = threading.Timer(INTERRUPT_GRACE_S, _stop_now, args=(_INTERRUPTED_LINE,))
    timer.daemon = True
    timer.start()
    raise KeyboardInterrupt


def _stop_now(line: str) -> NoReturn:
    """Say ``line``, stop the Prefect API server this process started (still running when
    only pipescan got the SIGINT) and end the process without the interpreter's exit hooks."""
    from pipescan.flows.housekeeping import prefect_servers_started_here, stop_orphaned_server

    for server in prefect_servers_started_here():  # first: what it says comes before
        stop_orphaned_server(server)
    if os.isatty(2):  # a progress bar hides the cursor while it draws: give it back
        os.write(2, b"\x1b[?25h")
    os.write(2, line.encode())
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(INTERRUPTED_EXIT_CODE)


def _interrupted() -> NoReturn:
    """The command was interrupted and has unwound."""
    _stop_now(_INTERRUPTED_LINE)


def _catch_interrupts() -> Any:
    """Handle Ctrl-C as :func:`_on_interrupt` says, unless SIGINT is ignored (a background job
    of a non-interactive shell) or handled by whoever called the command; the handler it
    replaced (to put back), or None."""
    _INTERRUPTED.clear()
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGINT)
    if previous is not signal.default_int_handler:
        return None
    signal.signal(signal.SIGINT, _on_interrupt)
    return previous


class _WholeHelpGroup(TyperGroup):
    """A group whose ``--help`` lists each command with its whole first sentence."""

    def format_commands(self, ctx: Any, formatter: Any) -> None:
        """The commands with their whole first sentence, wrapped, not cut at the width."""
        rows = []
        for name in self.list_commands(ctx):
            command = self.get_command(ctx, name)
            if command is not None and not command.hidden:
                rows.append((name, command.get_short_help_str(limit=1_000)))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


class _PipescanGroup(_WholeHelpGroup):
    """The top-level command: every error a user can cause is one line on stderr.

    - A :class:`PipescanError` (bad archive, bad option, unknown inspection, ...) and a usage
      error (a bad option value, a missing argument) print ``error: ...`` and exit with 2;
      with ``--debug`` or ``PIPESCAN_DEBUG=1`` the traceback comes first.
    - Anything else is a bug: its traceback, then a line saying how to report it; exit 1.
    - Ctrl-C, and whatever fails after it, is ``error: interrupted: ...`` and exit 130.
    """

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        args, kwargs = _take_debug(args, kwargs)
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        previous = _catch_interrupts()
        try:
            self._standalone(*args, **kwargs)
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    def _run(self, *args: Any, **kwargs: Any) -> Any:
        """The command; after a Ctrl-C, whatever it ends with (an exception, Prefect's API
        server stopped by the same Ctrl-C; click's Abort; typer's exit code 130) is the
        interrupt, not a bug."""
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except BaseException:
            if _INTERRUPTED.is_set():
                _interrupted()
            raise
        if _INTERRUPTED.is_set():
            _interrupted()
        return code

    def _standalone(self, *args: Any, **kwargs: Any) -> NoReturn:
        try:
            code = self._run(*args, **kwargs)
        except KeyboardInterrupt:
            _interrupted()
        except click_errors.NoArgsIsHelpError as exc:
            exc.show()  # the help text itself
            sys.exit(exc.exit_code)
        except click_errors.UsageError as exc:
            where = exc.ctx.command_path if exc.ctx is not None else "pipescan"
            _error_line(f"{exc.format_message()} (see `{where} --help`)")
            sys.exit(2)
        except click_errors.ClickException as exc:
            _error_line(exc.format_message())
            sys.exit(exc.exit_code)
        except typer.Abort:
            typer.echo("aborted", err=True)
            sys.exit(1)
        except PipescanError as exc:
            if _debugging():
                traceback.print_exception(exc)
            _error_line(str(exc))
            sys.exit(2)
        except OSError as exc:
            if exc.errno == errno.EPIPE:  # output piped into `head`: not an error
                sys.stdout = PacifyFlushWrapper(sys.stdout)  # type: ignore[assignment]
                sys.exit(1)
            _unexpected(exc)
        except Exception as exc:
            expected = _prefect_did_not_start(exc)
            if expected is None:
                _unexpected(exc)
            if _debugging():
                traceback.print_exception(exc)
            _error_line(str(expected))
            sys.exit(2)
        sys.exit(code if isinstance(code, int) else 0)


def _take_debug(args: tuple, kwargs: dict) -> tuple[tuple, dict]:
    """``--debug`` anywhere on the command line (``pipescan inspect x --debug`` as well as
    ``pipescan --debug inspect x``), taken out of the arguments before they are parsed; not
    after ``--``, where an argument is an argument."""
    given = kwargs.get("args", args[0] if args else None)
    argv = list(sys.argv[1:] if given is None else given)
    end = argv.index("--") if "--" in argv else len(argv)
    _DEBUG["on"] = "--debug" in argv[:end]
    kept = [a for a in argv[:end] if a != "--debug"] + argv[end:]
    if args:
        return (kept, *args[1:]), kwargs
    return (), {**kwargs, "args": kept}


def _prefect_did_not_start(exc: BaseException) -> OptionError | None:
    """Prefect's failure to start its temporary API server, as one line: it is the machine's
    state (busy), not a bug, and the user can act on it."""
    if not (isinstance(exc, RuntimeError) and "ephemeral Prefect API server" in str(exc)):
        return None
    return OptionError(
        "Prefect's temporary API server did not start in time (the machine may be busy)",
        hint="raise PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS (90 s now), or run "
        "`prefect server start` and set PREFECT_API_URL",
    )


def _unexpected(exc: BaseException) -> NoReturn:
    traceback.print_exception(exc)
    typer.secho(
        f"pipescan {pipescan.__version__} failed unexpectedly: this is a bug. Please report it "
        "with the command you ran and the traceback above.",
        fg=typer.colors.RED,
        err=True,
    )
    sys.exit(1)


HELP_MARKUP = None
"""``--help`` as plain text, not rich's panels: at 80 columns rich squeezes an option's help
into a third of the width and cuts examples short with "…", and reads ``[default: ...]`` in
a help text as markup (it vanished). Plain text wraps to the terminal and shows all of it."""

app = typer.Typer(
    cls=_PipescanGroup,
    help="Measure the inside of underground pipes from LiDAR scans.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=HELP_MARKUP,
)
export_app = typer.Typer(
    cls=_WholeHelpGroup,
    help="Export stored results (CSV, JSON lines, ISYBAU XML, GIS layers).",
    no_args_is_help=True,
    rich_markup_mode=HELP_MARKUP,
)
db_app = typer.Typer(
    cls=_WholeHelpGroup,
    help="Database schema management.",
    no_args_is_help=True,
    rich_markup_mode=HELP_MARKUP,
)
app.add_typer(export_app, name="export")
app.add_typer(db_app, name="db")

DbOption = Annotated[
    str | None,
    typer.Option(
        "--db",
        help="Database URL, or a SQLite file's path [env PIPESCAN_DATABASE_URL; "
        "default sqlite:///pipescan.db]",
    ),
]

ContourOption = Annotated[
    str | None,
    typer.Option(
        help=f"Contour method: {' or '.join(CONTOUR_METHODS)} "
        f"(env PIPESCAN_CONTOUR_METHOD; default {DEFAULT_CONTOUR_METHOD})."
    ),
]

RegistrationOption = Annotated[
    str | None,
    typer.Option(
        help="Registration method: gicp, point_to_plane or the paper's point_to_point "
        "(env PIPESCAN_REGISTRATION_METHOD; default gicp; docs/registration.md)."
    ),
]


class Scenario(StrEnum):
    paper = "paper"
    clean = "clean"
    long = "long"
    ring = "ring"
    static = "static"


class ExportFormat(StrEnum):
    csv = "csv"
    jsonl = "jsonl"


def _settings():
    """The settings, or one line naming the variable that is wrong (a pydantic error would be
    a page of traceback)."""
    from pydantic import ValidationError

    from pipescan.settings import get_settings

    try:
        return get_settings()
    except ValidationError as exc:
        first = exc.errors()[0]
        name = "PIPESCAN_" + "_".join(str(part) for part in first["loc"]).upper()
        raise OptionError(
            f"{name}={first.get('input')!r}: {first['msg']}",
            hint="fix it in the environment or in .env",
        ) from None


def _db_url(db: str | None) -> str:
    from pipescan.settings import as_database_url, database_url  # with a Secret's password

    return as_database_url(db) if db else database_url(_settings())


def _stored_db_url(db: str | None) -> str:
    """The database URL for a command that only reads: a SQLite file that does not exist is
    refused (``connect`` would create an empty one, and the command would then report on
    nothing), naming the URL and where it came from. A server database is checked by
    ``connect`` (which refuses one without pipescan's tables)."""
    from sqlalchemy.engine import make_url

    from pipescan.settings import Settings

    url = _db_url(db)
    try:
        parsed = make_url(url)
    except Exception:  # connect() says what is wrong with the URL
        return url
    database = parsed.database or ""
    if (
        parsed.get_backend_name() != "sqlite"
        or database in ("", ":memory:")
        or database.startswith("file:")
        or Path(database).expanduser().exists()
    ):
        return url
    if db:
        origin = "--db"
    elif url != Settings.model_fields["database_url"].default:
        origin = "PIPESCAN_DATABASE_URL"
    else:
        origin = "the default: no --db and no PIPESCAN_DATABASE_URL"
    shown = parsed.render_as_string(hide_password=True)
    raise OptionError(
        f"no database at {shown} ({origin}): {Path(database).expanduser().resolve()} "
        "does not exist",
        hint="give the database `pipescan inspect` wrote with --db or PIPESCAN_DATABASE_URL",
    )


class _StderrHandler(logging.StreamHandler):
    """The CLI's log lines, to whatever ``sys.stderr`` is when a line is written (not the
    stream it was when the command started, which a caller may have closed since)."""

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def _setup_logging(verbose: bool) -> None:
    if verbose:
        os.environ["PREFECT_LOGGING_LEVEL"] = "INFO"
        for name in _RUN_LOGGER_HANDLERS:
            os.environ[name] = "api,console"
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s  %(message)s", datefmt="%H:%M:%S"))
    logger = logging.getLogger("pipescan")
    # Replace only the CLI's own handler: Prefect's, which sends the lines of a flow run to
    # its API (PREFECT_LOGGING_EXTRA_LOGGERS), stays when the command runs in a process that
    # had set Prefect's logging up before (a test session, a notebook calling ``app``).
    logger.handlers[:] = [
        *(h for h in logger.handlers if not isinstance(h, _StderrHandler)),
        handler,
    ]
    logger.setLevel(logging.INFO)
    logger.propagate = False


_FORMAT_NAMES = {"pdf": "PDF", "png": "PNG", "svg": "SVG"}


def output_format(
    path: Path, *, option: str, what: str, formats: tuple[str, ...], bare: str | None = None
) -> str:
    """The format an output path's suffix names, one of ``formats`` (``"pdf"``, ``"png"``,
    ``"svg"``); a name without a suffix is ``bare``. Any other suffix is one line, before any
    work: the file would not be what its name says.

    >>> output_format(Path("out/trend.svg"), option="--plot", what="plot", formats=("png", "svg"))
    'svg'
    """
    suffix = path.suffix.lower().lstrip(".")
    if suffix in formats:
        return suffix
    if not suffix and bare is not None:
        return bare
    names = " or ".join(f".{f}" for f in formats)
    if suffix in _FORMAT_NAMES:
        reason = f"a {what} is written as {', '.join(_FORMAT_NAMES[f] for f in formats)} only"
    elif suffix:
        reason = f".{suffix} is not a format pipescan writes a {what} in"
    else:
        reason = "the name has no suffix to say the format"
    hint = f"end the name in {names}"
    if what == "report" and suffix == "png":
        hint += " (`pdftoppm -png` turns its pages into PNG images)"
    raise OptionError(f"{option} {path}: {reason}", hint=hint)


def make_output_folder(path: Path, what: str, kind: str) -> None:
    """Create the folder an output goes into, as every command does (CSV, JSON lines, PDF,
    XML, GeoPackage, plots); a path that names a folder, or runs through a file, is one line.

    Raises
    ------
    OutputError
        Naming the path and what is wrong.
    """
    from pipescan.core.errors import OutputError
    from pipescan.reports.render import check_output_path

    check_output_path(path, what, kind)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"cannot make the {what}'s folder: {exc.strerror or exc}",
            file=str(path),
            hint=f"give the path of a {kind} file in a folder you can write to",
        ) from exc


def _fail(exc: Exception) -> NoReturn:
    """Stop the command with an expected error: one line, exit code 2 (see _PipescanGroup)."""
    if isinstance(exc, PipescanError):
        raise exc
    raise OptionError(str(exc)) from exc


@app.callback()
def main(
    verbose: Annotated[
        bool, typer.Option("--verbose", "-v", help="Show Prefect's own logs.")
    ] = False,
    debug: Annotated[
        bool,
        typer.Option("--debug", help="Show the traceback of every error (env PIPESCAN_DEBUG=1)."),
    ] = False,
) -> None:
    if debug:
        _DEBUG["on"] = True
    _setup_logging(verbose)
