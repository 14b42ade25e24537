"""The ``proceduralize`` command line: one argparse subcommand per task.

Exit codes: 0 ok, 1 some failures, 2 bad input or usage (any ProceduralizeError: message to stderr).

Each subcommand is one module in :mod:`service.commands`. TO ADD A SUBCOMMAND:
  1. write ``service/commands/<name>.py`` with ``register(sub) -> None``, which creates the parser with
     ``sub.add_parser(..., parents=[common_parser()])`` (``service.commands.common``), adds its arguments and calls
     ``p.set_defaults(handler=handle)``, and the handler ``handle(args) -> int`` (the exit code); heavy modules
     (torch, ray, scipy through workers.graph, OpenImageIO through workers.maps, the SQLite store) are imported
     inside the handler, so ``proceduralize --help`` stays fast (tests/test_cli.py checks it);
  2. add the module to ``COMMANDS`` below, where the help lists it.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys

from pptbf_db.errors import ProceduralizeError
from service.commands import (
    db,
    demo,
    edit,
    evaluate,
    export,
    inspect,
    mask,
    render,
    report,
    results,
    run,
    status,
    submit,
)

logger = logging.getLogger("proceduralize")

#: the subcommand modules, in the order ``proceduralize --help`` lists them
COMMANDS = (inspect, render, demo, run, submit, status, results, db, report, edit, export, mask, evaluate)


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every subcommand of ``COMMANDS``."""
    parser = argparse.ArgumentParser(
        prog="proceduralize",
        description="Turn pixel SVBRDF maps into procedural, editable, resolution-free material graphs.",
        epilog="Exit codes: 0 ok, 1 some failures, 2 bad input or usage. "
               "'proceduralize COMMAND --help' describes each command.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for command in COMMANDS:
        command.register(sub)
    return parser


def _setup_logging(verbosity: int) -> None:
    """WARNING by default, INFO with -v, DEBUG with -vv."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", force=True)


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv``, run the subcommand and return its exit code (0 ok, 1 failures, 2 bad input/usage)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code) if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    _setup_logging(getattr(args, "verbose", 0))
    try:
        return int(args.handler(args) or 0)
    except ProceduralizeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 1
    except BrokenPipeError:  # output piped into e.g. `head`, which closed early: not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at interpreter exit
        return 0
    except Exception as exc:  # noqa: BLE001 - the CLI reports, logs the traceback with -v, and fails
        logger.debug("unexpected failure", exc_info=True)
        print(f"error: {type(exc).__name__}: {exc} (run with -vv for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
