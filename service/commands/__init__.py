"""The ``proceduralize`` subcommands, one module each.

Each command module has ``register(subparsers) -> None``, which adds its parser (with
``parents=[common.common_parser()]``) and sets its handler with ``p.set_defaults(handler=...)``; the handler takes
the parsed arguments and returns the exit code. :mod:`service.cli` lists the modules in help order.
Shared helpers: :mod:`service.commands.common` (parser pieces, tables, map files) and
:mod:`service.commands.jobs` (finding a job from a JOB reference).
"""
