"""`resim shards ...`: inspect WebDataset shard datasets. Imports only numpy/pyarrow/webdataset."""
from __future__ import annotations

import argparse
import json


def _cmd_schema(args: argparse.Namespace) -> int:
    from shards.schema import schema_dict

    print(json.dumps(schema_dict(), indent=2))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "shards",
        help="inspect shard datasets (ls, stats, show, verify, preview, schema)",
        description="Inspect a resim shard dataset (a folder with shards/, index/, manifest/, prompts/).",
    )
    sub = p.add_subparsers(dest="shards_command", metavar="SUBCOMMAND")
    s = sub.add_parser("schema", help="print the sample schema (members, metadata fields) as JSON")
    s.set_defaults(func=_cmd_schema)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
