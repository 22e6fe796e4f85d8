"""The ``memgs`` command line: one module per subcommand under ``memgs_ros.cli``.

Each subcommand module defines ``HELP: str``, ``add_arguments(parser)`` and
``run(args) -> int``, and keeps heavy imports inside ``run`` so ``memgs --help`` is fast.
Known errors (``MemgsError``) print one line and exit 2; so do operating-system errors the user
can fix (disk full, permission denied, a path that vanished): only bugs show a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from memgs_ros.errors import MemgsError
from memgs_ros.orchestration.signals import exit_status

# Subcommand name -> module under memgs_ros.cli.
SUBCOMMANDS: dict[str, str] = {
    "demo": "demo",
    "run": "run",
    "synth": "synth",
    "convert": "convert",
    "eval": "evaluate",
    "view": "view",
    "doctor": "doctor",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="memgs", description="MemGS Gaussian-splatting SLAM tools")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module_name in SUBCOMMANDS.items():
        module = importlib.import_module(f"memgs_ros.cli.{module_name}")
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    try:
        return int(args._run(args) or 0)
    except MemgsError as err:
        print(f"memgs {args.command}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # str() names the errno text and the file
        print(f"memgs {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM / SIGHUP (orchestration/signals.py)
        status, name = exit_status(err)
        print(f"memgs {args.command}: interrupted ({name}); the nodes were stopped", file=sys.stderr)
        return status


if __name__ == "__main__":
    sys.exit(main())
