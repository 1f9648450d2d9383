"""``lrms recipe export``: a stored recipe as TOML (the latest version, or one named)."""

from __future__ import annotations

import argparse

from service.cli._recipes import add_store_arguments, recipe_store

HELP = "write a stored recipe as TOML (to FILE, or to stdout)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", help="recipe name")
    parser.add_argument("file", metavar="FILE.toml", nargs="?", help="where to write it (default: stdout)")
    parser.add_argument("--version", type=int, metavar="N", help="this version (default: the latest)")
    add_store_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import sys
    from pathlib import Path

    from service.recipes import to_toml

    with recipe_store(args) as store:
        r = store.latest(args.name) if args.version is None else store.version(args.name, args.version)
    text = to_toml(r, r.version)
    if args.file is None:
        sys.stdout.write(text)
    else:
        Path(args.file).write_text(text, encoding="utf-8")
        print(f"{r.name} version {r.version} -> {args.file}", file=sys.stderr)
    return 0
