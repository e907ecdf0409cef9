"""``python -m unitysim``: play (what a launcher execs), build launchers, editor mode, list."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

# gRPC's event-engine client costs ~30% more CPU per unary call than the classic one
# (measured: 245-278 vs 176-181 us per exchange); the player makes one call per step.
# Set before grpc is first imported; an explicit GRPC_EXPERIMENTS wins.
os.environ.setdefault("GRPC_EXPERIMENTS", "-event_engine_client")
from collections.abc import Sequence

from unitysim.envs import NAMES
from unitysim.faults import Faults
from unitysim.player import CLIENT_VARIABLE, CLIENTS, Player, PlayerConfig

EDITOR_PORT = 5004


def _logging(log_file: str | None) -> None:
    """Like a player's ``-logFile``: everything there; only warnings on stderr."""
    root = logging.getLogger("unitysim")
    root.setLevel(logging.INFO)
    stderr = logging.StreamHandler(sys.stderr)
    stderr.setLevel(logging.WARNING)
    stderr.setFormatter(logging.Formatter("unitysim: %(message)s"))
    root.addHandler(stderr)
    if log_file:
        if log_file != "-":  # a player creates its log's folder, as Unity does
            Path(log_file).parent.mkdir(parents=True, exist_ok=True)
        handler = (
            logging.StreamHandler(sys.stdout)
            if log_file == "-"
            else logging.FileHandler(log_file, mode="w")
        )
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        root.addHandler(handler)


def _play(args: argparse.Namespace, port: int, watch_parent: bool) -> int:
    _logging(args.log_file)
    config = PlayerConfig(
        env_name=args.env,
        port=port,
        connect_timeout=args.connect_timeout,
        faults=Faults.from_arguments(args),
        watch_parent=watch_parent,
        client=args.grpc_client,
        no_graphics=getattr(args, "nographics", False),
    )
    logging.getLogger("unitysim").info("unitysim %s starting: %s", args.env, sys.argv[1:])
    return Player(config).run()


def _cmd_play(args: argparse.Namespace) -> int:
    if args.port is None:
        print(
            "unitysim: no --mlagents-port given; a build only connects to a trainer with it",
            file=sys.stderr,
        )
        return 2
    return _play(args, args.port, watch_parent=not args.no_parent_watch)


def _cmd_editor(args: argparse.Namespace) -> int:
    return _play(args, args.port, watch_parent=False)


def _cmd_build(args: argparse.Namespace) -> int:
    from unitysim.launcher import build

    for path in build(args.directory, args.env or NAMES):
        print(path)
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    from unitysim.envs import load

    for name in NAMES:
        env = load(name)
        print(f"{name:<18} {', '.join(b.name for b in env.behaviors)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m unitysim", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def player_options(sub: argparse.ArgumentParser) -> None:
        sub.add_argument("--env", required=True, choices=NAMES, help="environment to play")
        sub.add_argument("-logFile", "--log-file", dest="log_file", help="player log file")
        sub.add_argument(
            "--connect-timeout", type=float, default=30.0, help="seconds to wait for a trainer"
        )
        sub.add_argument(
            "--grpc-client",
            choices=CLIENTS,
            default=os.environ.get(CLIENT_VARIABLE) or CLIENTS[0],
            help=f"gRPC client: our HTTP/2 one or grpcio's (default: ${CLIENT_VARIABLE} or h2)",
        )
        Faults.add_arguments(sub)

    play = commands.add_parser("play", help="be a Unity build (launchers exec this)")
    player_options(play)
    play.add_argument("--mlagents-port", dest="port", type=int, help="the trainer's port")
    play.add_argument(
        "-nographics",
        action="store_true",
        help="as a Unity player: nothing is rendered, so camera sensors send blank frames",
    )
    play.add_argument("-batchmode", action="store_true", help="ignored, as headless")
    play.add_argument(
        "--no-parent-watch",
        action="store_true",
        help="do not exit when the launching process dies (to test launchers' own guards)",
    )
    play.set_defaults(func=_cmd_play)

    editor = commands.add_parser("editor", help="connect like pressing Play in the editor")
    player_options(editor)
    editor.add_argument("--port", type=int, default=EDITOR_PORT, help="trainer port (5004)")
    editor.set_defaults(func=_cmd_editor, connect_timeout=120.0)

    build = commands.add_parser("build", help="write <DIR>/<Env>.x86_64 launchers")
    build.add_argument("directory")
    build.add_argument("--env", action="append", choices=NAMES, help="only these (repeatable)")
    build.set_defaults(func=_cmd_build)

    listing = commands.add_parser("list", help="list the environments and their behaviors")
    listing.set_defaults(func=_cmd_list)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    # Unity players ignore arguments they do not know; so do we.
    args, unknown = parser.parse_known_args(argv)
    if unknown and args.command not in ("play", "editor"):
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
