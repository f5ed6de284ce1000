"""The ``bradyscope`` command line (INTERFACES.md).

Each sub-command lives in its own module with ``register(subparsers)`` that
adds its parser and sets ``func(args) -> int``. Domain errors become one
sentence on stderr and a non-zero exit status, never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from app.cli import admin, analyze, calibrate, serve, simulate, worker
from app.errors import AppError
from core.errors import BradyscopeError

# Sub-command modules, in the order they appear in --help.
_COMMANDS = (simulate, calibrate, analyze, serve, worker, admin)

EXIT_BAD_INPUT = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bradyscope",
        description="Measure finger tapping in 3D with two cameras.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debugging detail")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in _COMMANDS:
        command.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except (BradyscopeError, AppError) as exc:
        print(f"bradyscope {args.command}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"bradyscope {args.command}: interrupted.", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
