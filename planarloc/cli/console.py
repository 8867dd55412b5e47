"""Where the command line writes: results and information to stdout, progress and diagnostics to stderr.

- :func:`info`: what a command is for — summaries, ``map info``, the tables of ``evaluate`` and
  ``demo``, the files it wrote. When the results themselves go to stdout (``--out -``),
  :func:`results_on_stdout` sends information to stderr, so that stdout holds only the results.
- :func:`note`: warnings and diagnostics (a query that could not be processed, ``map check``'s
  problems, the ``serve`` banner), on stderr.
- :func:`progress_bar`: one bar per stage on stderr (plain lines without a terminal).

Lines are never hard-wrapped (paths and commands stay copy-pasteable). When the output is not a
terminal (a file, a pipe, CI logs) a table is printed whole, at its natural width (at least 120
columns): no column is squeezed, wrapped or cut with "…". On a terminal it fits the window.
Library code only receives plain callbacks (``progress(stage, done, total)``, ``notify(line)``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import cast

from rich.console import Console, RenderableType
from rich.errors import NotRenderableError
from rich.measure import Measurement

from planarloc.cli.progress import progress_reporter

#: Columns of a table when the output is a file or a pipe (rich would assume 80); wider tables
#: get their natural width (:func:`_print`).
MIN_TABLE_WIDTH = 120
#: Upper bound of a table's natural width off a terminal (rich measures up to the width it is given).
_MAX_PLAIN_WIDTH = 10_000


def _console(stderr: bool) -> Console:
    c = Console(stderr=stderr, soft_wrap=True, highlight=False)
    if not c.is_terminal:
        c.width = max(c.width, MIN_TABLE_WIDTH)  # logs and CI: do not squeeze tables to 80 columns
    return c


stderr_console = _console(stderr=True)
_info = {"console": _console(stderr=False)}


def _natural_width(console: Console, obj: object, markup: bool) -> int:
    """Columns ``obj`` needs to print without wrapping or cutting a cell (0 for plain text, which
    soft-wraps and is never cut); measured as printed, with ``markup`` (``"[ms]"`` is text then)."""
    if isinstance(obj, str):
        return 0
    options = console.options.update(markup=markup).update_width(_MAX_PLAIN_WIDTH)
    try:
        return Measurement.get(console, options, cast("RenderableType", obj)).maximum
    except NotRenderableError:  # e.g. a Path: printed as its text
        return 0


def _print(console: Console, objects: tuple[object, ...], markup: bool) -> None:
    """Print on ``console``; off a terminal, tables at their natural width (module docstring)."""
    if console.is_terminal:
        console.print(*objects, markup=markup)
        return
    width = max([console.width, *(_natural_width(console, o, markup) for o in objects)])
    if width == console.width:
        console.print(*objects, markup=markup)
        return
    saved = console.width
    console.width = width  # rich caps a print's width at the console's
    try:
        console.print(*objects, markup=markup)
    finally:
        console.width = saved


def results_on_stdout() -> None:
    """The results go to stdout: send information to stderr from now on."""
    _info["console"] = stderr_console


def info(*objects: object, markup: bool = False) -> None:
    """Print information (stdout, or stderr while results use stdout); ``markup``: rich markup."""
    _print(_info["console"], objects, markup)


def note(*objects: object, markup: bool = False) -> None:
    """Print a diagnostic on stderr (``markup``: the text uses rich markup, e.g. ``[yellow]``)."""
    _print(stderr_console, objects, markup)


def notify(line: str) -> None:
    """Print one notice line from the library (e.g. what a map build updated) on stderr, as is."""
    note(line)


@contextmanager
def progress_bar() -> Iterator[Callable[[str, int, int], None]]:
    """Yield ``update(stage, done, total)``: one bar per stage on stderr, plain lines when stderr
    is not a terminal (:mod:`planarloc.cli.progress`)."""
    with progress_reporter(stderr_console) as update:
        yield update
