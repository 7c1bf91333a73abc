"""`resim shards ...`: inspect WebDataset shard datasets. Imports only numpy/pyarrow/webdataset
(preview also needs matplotlib and OpenCV, imported in its handler)."""
from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from pathlib import Path

from resim.argtypes import positive_int as _positive_int, wrap as _wrap

# Every `resim` call imports this module to register its subcommands, so `resim --help` stays fast only if shards
# itself (and numpy, pyarrow; webdataset, which pulls in torch; matplotlib for previews) is imported inside the
# handler that needs it: the imports inside the functions below are that, not an oversight.

DATASET_HELP = "dataset folder (holds shards/, index/, manifest/, prompts/)"
KEY_HELP = "sample key (list them with `resim shards ls DIR --samples`)"

LS_EPILOG = """\
examples:
  resim shards ls out/shards                              # shards: samples, MiB, committed or not
  resim shards ls out/shards --samples --limit 5          # sample keys (the KEY of show/preview/sample/plan)
  resim shards ls out/shards --samples --source navsim --json
"""

STATS_EPILOG = """\
--json prints one JSON object with these keys:
  root, num_shards, num_samples, shard_bytes, uncommitted_shards, manifest_mismatch, schema_versions, config_hashes
  by_source, by_command, by_command_source, by_hazard ("true"/"false"/"null"), by_source_command
  turning_share            fraction of samples whose command is not "Moving forward"
  quarantine               {num_items, by_source, by_stage, by_reason, items[:20]} from DIR/quarantine/*.parquet:
                           the rows that kept an item out (status quarantined or dropped)
  warnings                 the same keys for status "warning" rows (the unit was used; e.g. a NaN compass)
  bytes_per_sample         mean bytes per member (meta.json, latent.npy, traj.npy, frames.mp4, dino.npy),
                           tar_overhead, in_shards, prompt_table_amortised, total
  member_presence          samples carrying each member
  latent                   {shapes: {"TxCxhxw": n}, dtypes: {name: n}}
  prompt_table             {num_prompts, bytes, entries: [{id, role, command, text, shape, dtype, encoder_id,
                           placeholder, num_tokens, bytes}]}
(see resim/shards/stats.py and docs/data_format.md)

example:
  resim shards stats out/shards --json > stats.json
"""


def _cmd_schema(args: argparse.Namespace) -> int:
    from resim.shards.schema import schema_dict

    print(json.dumps(schema_dict(), indent=2))
    return 0


def _cmd_ls_samples(args) -> int:
    from resim.shards.manifest import read_manifest

    rows = [{k: r[k] for k in ("key", "source", "command", "shard")} for r in read_manifest(args.dir).to_pylist()
            if args.source is None or r["source"] == args.source]
    total = len(rows)
    if args.limit is not None:
        rows = rows[:args.limit]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    if not rows:
        print(f"no samples in {args.dir}" + (f" with source {args.source}" if args.source else ""))
        return 0
    w = max(len(r["key"]) for r in rows)
    print(f"{'key':<{w}}  {'source':<9} {'command':<15} shard")
    for r in rows:
        print(f"{r['key']:<{w}}  {r['source']:<9} {r['command']:<15} {r['shard']}")
    print(f"{len(rows)} of {total} samples" if len(rows) < total else f"{total} samples")
    return 0


def _cmd_ls(args) -> int:
    from resim.shards import layout
    from resim.shards.manifest import read_indexes

    if args.samples:
        return _cmd_ls_samples(args)
    if args.source is not None or args.limit is not None:
        print("resim shards ls: error: --source and --limit go with --samples", file=sys.stderr)
        return 2
    indexes = read_indexes(args.dir)
    committed = {i["shard"] for i in indexes}
    rows = [{"shard": i["shard"], "num_samples": i["num_samples"], "bytes": i["bytes"],
             "committed": True, "sha256": i["sha256"]} for i in indexes]
    rows += [{"shard": p.name, "num_samples": None, "bytes": p.stat().st_size, "committed": False, "sha256": None}
             for p in layout.all_shard_files(args.dir) if p.name not in committed]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    if not rows:
        print(f"no shards in {args.dir}")
        return 0
    print(f"{'shard':<48} {'samples':>8} {'MiB':>9}")
    for r in rows:
        n = r["num_samples"] if r["committed"] else "(uncommitted)"
        print(f"{r['shard']:<48} {n!s:>8} {r['bytes'] / 2**20:9.2f}")
    tot = sum(r["num_samples"] or 0 for r in rows)
    print(f"{len(rows)} shards, {tot} samples, {sum(r['bytes'] for r in rows) / 2**20:.2f} MiB")
    return 0


def _cmd_stats(args) -> int:
    from resim.shards.stats import compute_stats, format_stats

    st = compute_stats(args.dir)
    print(json.dumps(st, indent=1, default=str) if args.json else format_stats(st))
    if args.plot:
        from resim.shards.stats import plot_quality

        p = plot_quality(args.dir, args.plot)
        print(f"quality histograms: {p}", file=sys.stderr if args.json else sys.stdout)
    return 0


def _describe(v):
    import numpy as np

    if isinstance(v, np.ndarray):
        return {"shape": list(v.shape), "dtype": str(v.dtype)}
    if isinstance(v, (bytes, bytearray)):
        return {"bytes": len(v)}
    return None


def _cmd_show(args) -> int:
    from resim.shards.reader import find_sample

    try:
        s = find_sample(args.dir, args.key, latent_as="stored", attach_prompts=True)
    except KeyError as e:
        print(f"error: {e.args[0]}", file=sys.stderr)
        return 1
    fields = {k: _describe(v) for k, v in s.items() if not k.startswith("__") and k != "meta.json"}
    if "latent.npy" in fields and s["meta.json"]["latent_dtype"] == "bfloat16":
        fields["latent.npy"]["note"] = "bfloat16 stored as uint16 bits"
    from resim.shards.prompts import PromptTable

    table = PromptTable(args.dir)
    for field, pid in (("prompt_embedding", s["meta.json"]["prompt_id"]),
                       ("null_prompt_embedding", s["meta.json"]["null_prompt_id"])):
        info = table.info(pid)
        fields[field].update(stored_dtype=info["dtype"], text=info["text"], prompt_id=pid)
    out = {"key": s["__key__"], "shard": s["__url__"], "meta": s["meta.json"], "fields": fields}
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"key   {out['key']}\nshard {out['shard']}\nmeta:")
    for k, v in out["meta"].items():
        print(f"  {k:<24} {v}")
    print("fields:")
    for k, v in fields.items():
        print(f"  {k:<24} {v}")
    return 0


def _cmd_verify(args) -> int:
    from resim.shards.verify import verify

    progress = None
    if not args.quiet:
        progress = lambda shard: print(f"checking {shard}", file=sys.stderr)  # noqa: E731
    problems = verify(args.dir, decode_video=not args.no_video, progress=progress)
    for p in problems:
        print(p)
    if problems:
        print(f"verify: {len(problems)} problem(s) in {args.dir}", file=sys.stderr)
        return 1
    print(f"verify: OK ({args.dir})")
    return 0


def _cmd_split(args) -> int:
    from resim.config import ConfigError
    from resim.shards import split

    if args.heldout_fraction is None and args.seed is None and args.min_heldout_episodes is None:
        s = split.read(args.dir)
    else:
        old = split.read(args.dir).config
        try:
            cfg = split.SplitConfig(
                heldout_fraction=old.heldout_fraction if args.heldout_fraction is None else args.heldout_fraction,
                seed=old.seed if args.seed is None else args.seed,
                min_heldout_episodes=(old.min_heldout_episodes if args.min_heldout_episodes is None
                                      else args.min_heldout_episodes))
        except ConfigError as e:
            print(f"resim shards split: error: {e}", file=sys.stderr)
            return 2
        s = split.write(args.dir, cfg)
    if args.json:
        print(json.dumps({**s.summary(), "heldout": sorted(s.heldout), "topped_up": sorted(s.topped_up)}, indent=1))
        return 0
    c = s.config
    print(f"split of {args.dir}: {len(s.train)} episode(s) train, {len(s.heldout)} held out "
          f"(fraction {c.heldout_fraction}, seed {c.seed}, at least {c.min_heldout_episodes} per source"
          + (f"; {len(s.topped_up)} topped up" if s.topped_up else "") + f"); from {s.origin}")
    return 0


def _cmd_preview(args) -> int:
    import random

    from resim.shards.confine import UnsafePathError, confined
    from resim.shards.errors import ShardReadError
    from resim.shards.manifest import read_manifest
    from resim.shards.preview import render_preview
    from resim.shards.reader import find_sample

    if bool(args.key) == bool(args.random):
        print("error: give either KEY or --random N", file=sys.stderr)
        return 2
    # (folder, file name) per key: the name holds the key, a dataset value, so it is confined to the folder
    # (a key like ../../x must not write outside it); an --out file path the user chose is taken as is
    if args.key:
        keys = [args.key]
        out = Path(args.out or ".")
        into_folder = out.is_dir() or (args.out or "").endswith(("/", os.sep))   # a folder: write KEY.png into it
        if args.out is None:
            targets = [(out, f"preview-{args.key}.png")]
        else:
            targets = [(out, f"{args.key}.png") if into_folder else (None, out)]
    else:
        all_keys = read_manifest(args.dir)["key"].to_pylist()
        if not all_keys:
            print(f"error: no samples in {args.dir}", file=sys.stderr)
            return 1
        keys = random.Random(args.seed).sample(all_keys, min(args.random, len(all_keys)))
        folder = Path(args.out or "previews")
        targets = [(folder, f"{k}.png") for k in keys]
    skipped = 0
    for k, (folder, name) in zip(keys, targets):
        try:
            o = confined(folder, name, f"sample {k!r}: preview file") if folder is not None else name
            s = find_sample(args.dir, k, decode_video=True, attach_prompts=False)
        except KeyError as e:
            print(f"error: {e.args[0]}", file=sys.stderr)
            return 1
        except (UnsafePathError, ShardReadError) as e:   # a hostile key or a bad sample: the others still render
            print(f"resim shards preview: skipping {e}", file=sys.stderr)
            skipped += 1
            continue
        print(render_preview(s, o))
    return 1 if skipped else 0


def _on_dataset(cmd):
    """Runs ``cmd`` on an existing dataset folder; a dataset it cannot read (corrupt index or manifest, missing
    files) is a clear one-line error and exit status 1, not a traceback. Our own bugs still raise."""
    @functools.wraps(cmd)
    def run(args) -> int:
        from resim.shards import layout
        from resim.shards.errors import ShardReadError

        if not Path(args.dir).is_dir():
            print(f"resim shards {args.shards_command}: error: {args.dir} is not a folder", file=sys.stderr)
            return 1
        if args.shards_command != "verify" and not layout.shards_dir(args.dir).is_dir():
            # verify says so itself (one problem line, exit 1); the others used to print empty tables
            print(f"resim shards {args.shards_command}: error: {args.dir} has no shards/ folder (not a shard "
                  "dataset; `resim pipeline run` writes one)", file=sys.stderr)
            return 1
        try:
            return cmd(args)
        except BrokenPipeError:   # `... | head`: the reader left; handled quietly by run_quietly_piped
            raise
        except (ShardReadError, OSError) as e:
            print(f"resim shards {args.shards_command}: error: {e}", file=sys.stderr)
            return 1
    return run


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "shards",
        help="inspect shard datasets (ls, stats, show, verify, preview, split, schema); copy one adding features",
        description="Inspect a resim shard dataset (a folder with shards/, index/, manifest/, prompts/). "
        "The format is described in docs/data_format.md; `resim shards schema` prints it as JSON. "
        "`resim shards features` copies a dataset adding the reward model's DINOv2 features.",
    )
    sub = p.add_subparsers(dest="shards_command", metavar="SUBCOMMAND")

    s = sub.add_parser("ls", help="list shards with sample counts and sizes, or sample keys (--samples)",
                       description=_wrap("List shards with sample counts and sizes (uncommitted shards are marked); "
                       "with --samples, list the committed samples (key, source, command, shard) from the manifest."),
                       epilog=LS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("dir", help=DATASET_HELP)
    s.add_argument("--json", action="store_true", help="one JSON list of {shard, num_samples, bytes, committed, sha256} "
                   "(with --samples: of {key, source, command, shard})")
    s.add_argument("--samples", action="store_true", help="list sample keys instead of shards")
    s.add_argument("--source", default=None, help="with --samples: only this source (e.g. opendv, navsim, carla)")
    s.add_argument("--limit", type=_positive_int, default=None, metavar="N", help="with --samples: at most N rows")
    s.set_defaults(func=_on_dataset(_cmd_ls))

    s = sub.add_parser("stats", help="totals by source/command/hazard, bytes per sample, prompt table",
                       description="Totals by source, command and hazard; turning share; quarantined items; bytes "
                       "per sample split by member (prompt table amortised); latent shape/dtype; prompt table. "
                       "Reads manifests and indexes only (fast).",
                       epilog=STATS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("dir", help=DATASET_HELP)
    s.add_argument("--json", action="store_true", help="print one machine-readable JSON object (keys below)")
    s.add_argument("--plot", metavar="PNG", help="also draw the per-clip quality columns' histograms by source "
                   "(ego motion, brightness, contrast, sharpness, static edges, flow quality) into PNG: choose the "
                   "pipeline config's quality filters from them")
    s.set_defaults(func=_on_dataset(_cmd_stats))

    s = sub.add_parser("show", help="one sample's metadata and field shapes",
                       description=_wrap("Print one sample's metadata and the shape/dtype/size of each member."),
                       epilog="example:\n  resim shards show out/shards KEY --json      "
                       "# KEY from `resim shards ls out/shards --samples`",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("dir", help=DATASET_HELP)
    s.add_argument("key", help=KEY_HELP)
    s.add_argument("--json", action="store_true", help="print {key, shard, meta, fields} as JSON")
    s.set_defaults(func=_on_dataset(_cmd_show))

    s = sub.add_parser("verify", help="check shards against indexes, samples against the schema; exit 1 on problems",
                       description=_wrap("Check every shard against its index (sha256, size, counts, keys), that every "
                       "sample decodes and matches the schema, frames.mp4 decodes to the declared frames, every "
                       "prompt reference resolves, and no writer left temporary/uncommitted files. Prints one line "
                       "per problem naming shard and key. Exit status 0 only when everything holds, else 1."),
                       epilog="example:\n  resim shards verify out/shards --no-video -q",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("dir", help=DATASET_HELP)
    s.add_argument("--no-video", action="store_true", help="skip decoding frames.mp4 (faster)")
    s.add_argument("-q", "--quiet", action="store_true", help="no per-shard progress on stderr")
    s.set_defaults(func=_on_dataset(_cmd_verify))

    s = sub.add_parser("preview", help="PNG contact sheet of a sample (frames, command, heading, trajectory)",
                       description=_wrap("Write a PNG contact sheet of a sample's frames with its command, heading change "
                       "and trajectory (top-down inset). Needs matplotlib and OpenCV."),
                       epilog="examples:\n  resim shards preview out/shards KEY --out previews/   "
                       "# writes previews/KEY.png\n  resim shards preview out/shards --random 4 --out previews/",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("dir", help=DATASET_HELP)
    s.add_argument("key", nargs="?", help=KEY_HELP + "; or use --random N")
    s.add_argument("--random", type=_positive_int, metavar="N", help="preview N random samples instead of KEY")
    s.add_argument("--seed", type=int, default=0, help="seed for --random (default 0)")
    s.add_argument("--out", help="PNG path for KEY (default preview-KEY.png; an existing folder: FOLDER/KEY.png); "
                   "folder for --random (default previews/)")
    s.set_defaults(func=_on_dataset(_cmd_preview))

    s = sub.add_parser("split", help="show the train / held-out split by episode, or write it (split.json)",
                       description=_wrap("Show the dataset's train / held-out split: whole episodes (item_id) on one "
                       "side, held out when a seeded hash of the id falls below the fraction, each source topped up "
                       "to a minimum (docs/data_format.md, \"The split\"). The pipeline writes it to DIR/split.json; "
                       "every trainer and evaluator reads it. With any option, (re)write split.json: for a dataset "
                       "older than the split, or another split of the same episodes."),
                       epilog="examples:\n  resim shards split out/shards\n"
                       "  resim shards split out/shards --heldout-fraction 0.25 --seed 1",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("dir", help=DATASET_HELP)
    s.add_argument("--heldout-fraction", type=float, default=None, metavar="F",
                   help="share of the episodes held out, by hash (default: the dataset's, else 0.2)")
    s.add_argument("--seed", type=int, default=None, help="seed of the hash (default: the dataset's, else 0)")
    s.add_argument("--min-heldout-episodes", type=int, default=None, metavar="N",
                   help="at least N held-out episodes per source of 2 or more (default: the dataset's, else 1)")
    s.add_argument("--json", action="store_true", help="print the split's summary and held-out episodes as JSON")
    s.set_defaults(func=_on_dataset(_cmd_split))

    s = sub.add_parser("schema", help="print the sample schema (members, metadata fields) as JSON",
                       description=_wrap("Print the shard sample schema as JSON: the members of a sample (meta.json, "
                       "latent.npy, traj.npy, frames.mp4, dino.npy), the metadata fields with their types, and the "
                       "manifest columns. Needs no dataset; see docs/data_format.md."),
                       epilog="example:\n  resim shards schema > schema.json",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.set_defaults(func=_cmd_schema)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
