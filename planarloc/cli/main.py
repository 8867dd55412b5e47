"""The `planarloc` command line: map building, localization, evaluation and the demo."""

from __future__ import annotations

import argparse
import logging
import sqlite3
import sys

from planarloc.cli import (
    cache_command,
    demo_command,
    evaluate_command,
    localize_command,
    map_command,
    ros2_command,
    serve_command,
    warmup_command,
)
from planarloc.cli.errors import os_error_message, sqlite_error_message
from planarloc.cli.exit_codes import EXIT_ERROR, EXIT_INTERRUPTED
from planarloc.cli.exit_codes import HELP as EXIT_CODES_HELP
from planarloc.extras import MissingExtraError
from planarloc.map.errors import MapKeyError
from planarloc.version import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="planarloc",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Localize a ground robot's camera against a map that is only a set of posed images "
        "(no 3D model), from 2D-2D matches under local planar motion.\n\n"
        "examples (start here):\n"
        "  planarloc demo                      map and localize a generated indoor world\n"
        "  planarloc map build DATA -f kitti --out map.db\n"
        "  planarloc localize --map map.db query.png --camera 'PINHOLE W H fx fy cx cy'\n"
        "  planarloc evaluate DATA -f kitti --map-every 2 --structure tracks",
        epilog=EXIT_CODES_HELP,
    )
    parser.add_argument("--version", action="version", version=f"planarloc {__version__}")
    parser.add_argument("--verbose", "-v", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in (
        demo_command,
        map_command,
        localize_command,
        evaluate_command,
        serve_command,
        ros2_command,
        warmup_command,
        cache_command,
    ):
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, sqlite3.Error, MapKeyError, MissingExtraError) as exc:
        # Known errors (bad input, bad files, file system, damaged maps, a missing optional
        # extra) print one line; anything else keeps its traceback.
        command = " ".join(filter(None, [args.command, getattr(args, "map_command", None)]))
        if isinstance(exc, OSError):
            text = os_error_message(exc)
        elif isinstance(exc, sqlite3.Error):
            text = sqlite_error_message(exc)
        elif isinstance(exc, MapKeyError):  # only the map's own: any other KeyError is a bug
            text = (
                f"map lookup failed ({exc.args[0] if exc.args else exc}); "
                "run `planarloc map check` on the map"
            )
        else:
            text = str(exc)
        print(f"planarloc {command}: error: {' '.join(text.split())}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        # Each command says what Ctrl-C leaves: its own message, its `interrupted` default, or nothing kept.
        print(str(exc) or getattr(args, "interrupted", None) or "interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
