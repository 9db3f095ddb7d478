"""`netpose schema`: the telemetry messages' key reference, as docs/telemetry.md carries it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from service.core.errors import NetposeError
from service.core.messages import schema_markdown

# The generated block in a Markdown file (docs/telemetry.md); a test keeps it current.
BEGIN = "<!-- schema:begin (netpose schema) -->\n"
END = "<!-- schema:end -->"


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "schema",
        help="print the telemetry schema (Markdown)",
        description="Print the key reference of every telemetry message (estimate, status, "
        "state, preview metadata) as Markdown, generated from the message types.",
    )
    p.add_argument("--update", type=Path, metavar="FILE", default=None,
                   help="replace the generated block of FILE (docs/telemetry.md) instead of "
                   "printing")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.update is None:
        print(schema_markdown(), end="")
        return 0
    text = args.update.read_text(encoding="utf-8")
    if BEGIN not in text or END not in text:
        raise NetposeError(f"{args.update}: no '{BEGIN.strip()}' ... '{END}' block to replace")
    head, rest = text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    args.update.write_text(head + BEGIN + schema_markdown() + END + tail, encoding="utf-8")
    return 0
