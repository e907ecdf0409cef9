"""The ``unity-rollout`` command line: the one place that wires the parts together.

Each sub-command is a small function taking parsed arguments; heavy imports happen inside
the command so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

Command = Callable[[argparse.Namespace], int]


def _cmd_doctor(args: argparse.Namespace) -> int:
    """Show which compatibility fixes this interpreter needs and the key package versions."""
    import platform
    from importlib import metadata

    from rollout import compat

    fixes = compat.install()
    import mlagents_envs.environment  # noqa: F401  (proves the import works)
    from google.protobuf.internal import api_implementation

    print(f"python            {platform.python_version()}")
    for dist in ("mlagents-envs", "protobuf", "grpcio", "numpy", "torch", "torchrl", "ray"):
        try:
            version = metadata.version(dist)
        except metadata.PackageNotFoundError:
            version = "not installed"
        print(f"{dist:<17} {version}")
    print(f"protobuf backend  {api_implementation.Type()}")
    print(f"compat fixes      {', '.join(fixes) or 'none needed'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="unity-rollout",
        description="Distributed rollouts for Unity ML-Agents environments on Ray.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    doctor = commands.add_parser("doctor", help="check that mlagents-envs imports here")
    doctor.set_defaults(func=_cmd_doctor)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    func: Command = args.func
    return func(args)


if __name__ == "__main__":
    sys.exit(main())
