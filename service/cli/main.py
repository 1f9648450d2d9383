"""Entry point of the ``lrms`` command.

Each command lives in its own module under :mod:`service.cli` and exposes::

    HELP: str                                   # one line for ``lrms --help``
    def configure(parser: argparse.ArgumentParser) -> None
    def run(args: argparse.Namespace) -> int   # the exit status

Command modules import only the standard library at module level (heavy imports go inside
``run``) so that ``lrms --help`` and every command start fast. Errors raised on purpose by the
packages (:class:`lrms.errors.LrmsError`, :class:`drivers.errors.DriverError`,
:class:`service.errors.ServiceError`) are printed as one ``error:`` line with exit status 1;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# (command words) -> module. A word list of two makes a sub-command group (``lrms sim scanner``).
COMMANDS: dict[tuple[str, ...], str] = {
    ("scan",): "service.cli.scan",
    ("motor",): "service.cli.motor",
    ("fit",): "service.cli.fit",
    ("calibrate",): "service.cli.calibrate",
    ("register",): "service.cli.register",
    ("brackets",): "service.cli.brackets",
    ("serve",): "service.cli.serve",
    ("measure",): "service.cli.measure",
    ("replay",): "service.cli.replay",
    ("db", "upgrade"): "service.cli.db",
    ("report",): "service.cli.report",
    ("reprocess",): "service.cli.reprocess",
    ("sim", "scanner"): "service.cli.sim_scanner",
    ("sim", "motor"): "service.cli.sim_motor",
    ("recipe", "import"): "service.cli.recipe_import",
    ("recipe", "export"): "service.cli.recipe_export",
}

GROUP_HELP = {
    "sim": "run a simulated device server (scanner or motor)",
    "db": "the result database",
    "recipe": "import or export a part recipe (TOML)",
}


class _Formatter(argparse.HelpFormatter):
    """Room for the longest command name (``calibrate``) beside its help."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog)
        self._action_max_length = 14


def build_parser() -> argparse.ArgumentParser:
    from lrms import __version__

    parser = argparse.ArgumentParser(
        prog="lrms",
        description="Laser radar measurement system",
        formatter_class=_Formatter,
    )
    parser.add_argument("--version", action="version", version=f"lrms {__version__}")
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    top.required = True
    groups: dict[str, argparse._SubParsersAction] = {}
    for words, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        if len(words) == 1:
            sub = top.add_parser(words[0], help=module.HELP, description=module.HELP)
        else:
            if words[0] not in groups:
                gp = top.add_parser(words[0], help=GROUP_HELP.get(words[0]))
                groups[words[0]] = gp.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True)
            sub = groups[words[0]].add_parser(words[1], help=module.HELP, description=module.HELP)
        module.configure(sub)
        sub.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from drivers.errors import DriverError
    from drivers.url import register
    from lrms.errors import LrmsError
    from service.errors import ServiceError

    # the sim:// device URLs, by dotted path: the simulator (numpy, python-can, the scene) is
    # imported only by a command that opens a simulated device, not by every start of ``lrms``
    register("scanner", "sim", "service.simdevices:open_sim_scanner")
    register("motor", "sim", "service.simdevices:open_sim_motor")
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        status: int = args._run(args)
    except (LrmsError, DriverError, ServiceError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return status


if __name__ == "__main__":
    sys.exit(main())
