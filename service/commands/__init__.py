"""Sub-commands of `netpose`; each module exposes `add_parser(subparsers)`."""
