"""The ``lightflow`` command line.

User errors (:class:`~lightflow.app.core.errors.LightflowError`) are printed as one
line, ``lightflow: error: ...``, with exit status 2 and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from lightflow.app import commands
from lightflow.app.core.errors import LightflowError
from lightflow.app.memory import keep_freed_memory

DESCRIPTION = """\
Depth of fast-moving objects from the motion blur of projected line patterns
(structured light flow).  Start with `lightflow demo`, which needs no hardware."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lightflow",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    keep_freed_memory()  # frame-sized buffers are reused, not faulted in again each frame
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        status = args.func(args)
    except LightflowError as exc:
        print(f"lightflow: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lightflow: interrupted", file=sys.stderr)
        return 130
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())
