"""The `tignn` command line.

Each subcommand lives in its own module that exposes ``register(subparsers)``; the module adds its parser and
sets ``func`` (called with the parsed namespace, returning an exit code). Modules are imported only to build the
parser, so `tignn --help` stays fast and one broken subcommand cannot hide the others.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# (module path) of every subcommand module, in the order they appear in --help.
COMMAND_MODULES = (
    "fem.cli",
    "tignn_jax.commands_model",
    "tignn_jax.commands_demo",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tignn",
        description="Thermodynamics-informed graph networks and a differentiable FEM in JAX.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
