"""How every subcommand is declared: a one-line summary, a description and commands to copy."""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable, Sequence


def reflow(text: str) -> str:
    """A help text written as an indented block: each paragraph (blank-line separated) becomes one
    line, so that the terminal wraps it; indented lines (lists, commands) stay as they are."""
    out: list[str] = []
    for paragraph in inspect.cleandoc(text).split("\n\n"):
        lines: list[str] = []
        for line in paragraph.splitlines():
            if line.startswith(" ") or not lines or lines[-1].startswith(" "):
                lines.append(line)
            else:
                lines[-1] += " " + line
        out.append("\n".join(lines))
    return "\n\n".join(out)


def add_command(
    sub: argparse._SubParsersAction,
    name: str,
    summary: str,
    description: str,
    examples: Sequence[str],
    func: Callable[[argparse.Namespace], int] | None = None,
    listing: str = "",
    **defaults: object,
) -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` shows ``description`` (:func:`reflow`) and ``examples``;
    ``listing``: preformatted lines shown after the description (e.g. a table of choices);
    ``func(args)`` runs it, ``defaults`` are set on its namespace (e.g. ``interrupted``)."""
    shown = "\n".join(f"  {e}" for e in examples)
    p = sub.add_parser(
        name,
        help=summary,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=f"{reflow(description)}{listing}\n\nexample{'s' if len(examples) > 1 else ''}:\n{shown}",
    )
    if func is not None:
        p.set_defaults(func=func, **defaults)
    return p
