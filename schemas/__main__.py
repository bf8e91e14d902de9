"""`python -m schemas export [DIR]` writes JSON Schema for every message;
`python -m schemas check` exits 1 when the checked-in files are stale;
`python -m schemas catalogue` prints the message catalogue as a markdown table."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import msgspec

from schemas.catalogue import markdown
from schemas.messages import ALL_MESSAGES

DEFAULT_DIR = Path(__file__).parent / "json"


def rendered() -> dict[str, str]:
    out = {}
    for msg in ALL_MESSAGES:
        schema = msgspec.json.schema(msg)
        out[f"{msg.__name__}.json"] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def export(directory: Path) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in rendered().items():
        path = directory / name
        path.write_text(text)
        written.append(path)
    return written


def stale(directory: Path) -> list[str]:
    wanted = rendered()
    problems = [n for n, t in wanted.items() if not (directory / n).is_file() or (directory / n).read_text() != t]
    problems += [p.name + " (no such message)" for p in directory.glob("*.json") if p.name not in wanted]
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m schemas", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p_export = sub.add_parser("export", help="write JSON Schema files (default: schemas/json/)")
    p_export.add_argument("directory", nargs="?", type=Path, default=DEFAULT_DIR)
    p_check = sub.add_parser("check", help="fail when the JSON Schema files are out of date")
    p_check.add_argument("directory", nargs="?", type=Path, default=DEFAULT_DIR)
    sub.add_parser("catalogue", help="print the key expression catalogue (markdown)")
    args = parser.parse_args(argv)
    if args.command == "export":
        for path in export(args.directory):
            print(path)
    elif args.command == "check":
        problems = stale(args.directory)
        if problems:
            print("stale JSON Schema (run `python -m schemas export`): " + ", ".join(problems), file=sys.stderr)
            return 1
        print(f"{len(ALL_MESSAGES)} JSON Schema files up to date")
    else:
        sys.stdout.write(markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
