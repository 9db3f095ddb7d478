"""`netpose schema`: the telemetry messages' key reference, as docs/telemetry.md carries it."""

from __future__ import annotations

import argparse
from typing import Any

from service.core.messages import schema_markdown


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "schema",
        help="print the telemetry schema (Markdown)",
        description="Print the key reference of every telemetry message (estimate, status, "
        "state, preview metadata) as Markdown, generated from the message types.",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    print(schema_markdown(), end="")
    return 0
