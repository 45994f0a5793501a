"""The ``tignn`` command line: one module per subcommand, each with ``register(subparsers)``.

A subcommand's ``func(args) -> int`` reports bad input by raising `UsageError` (or ``ValueError`` from the
library's own checks): `main` prints one line naming the bad value and exits with 2, without a traceback unless
``--debug`` is given. A path that cannot be read or written (``OSError``: missing, not a folder, no permission)
is reported the same way, naming the path.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = ("tignn_jax.cli.generate", "tignn_jax.cli.train", "tignn_jax.cli.evaluate", "tignn_jax.cli.rollout",
            "tignn_jax.cli.demo", "tignn_jax.cli.fem_example", "tignn_jax.cli.view", "tignn_jax.cli.track")


class UsageError(Exception):
    """Bad input from the command line: the message names the option and the bad value."""


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose errors (a missing, unknown or malformed option) are one line and exit code 2, as the
    subcommands' own: "PROG: error: MESSAGE (see PROG --help)", without the usage block."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="tignn", description="Thermodynamics-informed simulators of deformable bodies, and their FEM, in JAX.")
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (UsageError, ValueError, OSError) as err:
        if args.debug:
            raise
        if isinstance(err, OSError) and err.filename is not None and err.strerror:
            message = f"{err.filename}: {err.strerror}"
        else:
            message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"tignn {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
