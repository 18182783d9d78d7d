"""The ``jurs`` command line."""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jurs", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="fit the paper's Example 1 with IPIA and IURS")
    demo.add_argument("--output", default="demo-output", help="folder for the figure")
    args = parser.parse_args(argv)
    if args.command == "demo":
        from .demo import run

        run(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
