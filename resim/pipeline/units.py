"""Work units: one source item (video / log / route) each, and the small state that flows between stages.

A unit's state is a JSON-able dict (paths, labels, counts — never frames), so a Ray Data row stays
a few KB however long the video is; every stage that needs pixels decodes them itself at the size it
needs. The unit id is derived from (layout kind, item id) only, so it is stable across reruns and
machines; it doubles as the unit's shard prefix (``shards/<unit_id>-00000.tar``) and the name of its
commit marker (``commits/<unit_id>.json``), which is why reruns never collide or duplicate.
"""
from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from resim.config import ConfigError, from_dict, to_dict
from resim.pipeline.config import ClipConfig, PipelineConfig
from resim.pipeline.sources.carla import CarlaConfig, CarlaReader
from resim.pipeline.sources.navsim import NavsimConfig, NavsimReader
from resim.pipeline.sources.opendv import OpenDVConfig, OpenDVReader
from resim.pipeline.sources.synth.generate import SynthConfig

KINDS = ("opendv", "navsim", "carla")
_SAFE = re.compile(r"[^A-Za-z0-9]+")


def unit_id_for(kind: str, item_id: str) -> str:
    """Stable, filesystem- and shard-prefix-safe id: ``<kind>-<readable tail>-<sha 12>``.

    ``kind`` is the origin (``opendv`` or ``synthetic-opendv``) so a synthetic and a real item with
    the same relative path never share a prefix."""
    readable = _SAFE.sub("-", item_id).strip("-")[-32:] or "item"
    digest = hashlib.sha256(f"{kind}\0{item_id}".encode()).hexdigest()[:12]
    return f"{kind}-{readable}-{digest}"


@dataclass(frozen=True)
class SourceSpec:
    """One configured reader: a layout kind, its root, the config section it came from."""

    kind: str            # reader layout: opendv | navsim | carla
    root: str
    section: str         # config key, e.g. "sources.opendv" or "sources.synthetic"
    max_items: int | None
    options: tuple       # reader config fields as (key, value) pairs (hashable)
    clip: dict | None = None   # per-source clip geometry override (plain dict), None = top-level clip
    exclude: tuple[str, ...] = ()   # trees the reader never lists: OUT and its output folders (out_trees)

    @property
    def origin(self) -> str:
        """Label for reports: ``opendv`` or ``synthetic/opendv``."""
        return self.kind if self.section == f"sources.{self.kind}" else f"synthetic/{self.kind}"


# What a run writes in OUT as folders (its files are config.yaml, config_hash.txt, stats.json, report.png and
# the run lock); `runner.prepare_out` removes them all when a run with nothing committed is redone.
OUTPUT_DIRS = ("commits", "shards", "index", "manifest", "quarantine", "prompts", "_staging", "dedup")


def out_trees(out) -> tuple[str, ...]:
    """What no reader may list: OUT, and its output folders (these still apply when a source root lies inside
    OUT itself, where OUT as a whole cannot be excluded; ``resim.pipeline.sources.listing``)."""
    if out is None:
        return ()
    return (str(out), *(str(Path(out) / d) for d in OUTPUT_DIRS))


def source_specs(cfg: PipelineConfig) -> list[SourceSpec]:
    """The readers this config asks for (synthetic root expanded into its three layouts), none listing OUT."""
    specs = []
    s = cfg.sources

    def clip_of(c: ClipConfig | None) -> dict:
        return to_dict(c if c is not None else cfg.clip)

    if s.opendv.root is not None:
        c = s.opendv.clip or cfg.clip
        specs.append(SourceSpec("opendv", str(s.opendv.root), "sources.opendv", s.opendv.max_items, tuple(sorted({
            "start_discard_s": s.opendv.start_discard_s, "end_discard_s": s.opendv.end_discard_s,
            "min_height_px": s.opendv.min_height_px, "fps_hz": c.fps_hz}.items())), clip_of(c)))
    if s.navsim.root is not None:
        specs.append(SourceSpec("navsim", str(s.navsim.root), "sources.navsim", s.navsim.max_items,
                                tuple(sorted({"split": s.navsim.split, "camera": s.navsim.camera}.items())),
                                clip_of(s.navsim.clip)))
    if s.carla.root is not None:
        specs.append(SourceSpec("carla", str(s.carla.root), "sources.carla", s.carla.max_items,
                                tuple(sorted({"camera": s.carla.camera}.items())), clip_of(s.carla.clip)))
    if s.synthetic.root is not None:
        for kind in s.synthetic.layouts:
            c = s.synthetic.clip.get(kind) or cfg.clip
            opts: dict[str, Any] = {}
            if kind == "opendv":  # the synthetic world has no intro/outro and small frames
                opts = {"start_discard_s": 0.0, "end_discard_s": 0.0, "min_height_px": 32, "fps_hz": c.fps_hz}
            if kind == "navsim":
                opts = {"split": _synth_navsim_split(Path(s.synthetic.root))}
            specs.append(SourceSpec(kind, str(Path(s.synthetic.root) / kind), "sources.synthetic", None,
                                    tuple(sorted(opts.items())), clip_of(c)))
    # an OUT inside an input root must not be read back as input (its _staging previews are videos)
    return [replace(sp, exclude=out_trees(cfg.out)) for sp in specs]


def _synth_navsim_split(root: Path) -> str:
    """The split the synthetic world wrote its NAVSIM logs under (``synth_config.json``; default 'synth')."""
    p = root / "synth_config.json"
    if p.is_file():
        return str(json.loads(p.read_text()).get("navsim_split", "synth"))
    return SynthConfig().navsim_split


# source kind -> (reader config, reader class)
READERS = {"opendv": (OpenDVConfig, OpenDVReader), "navsim": (NavsimConfig, NavsimReader),
           "carla": (CarlaConfig, CarlaReader)}


def make_reader(spec: SourceSpec):
    """The sources package's reader for ``spec`` (the readers' interface: ``list_items()``, ``open(id)``)."""
    if spec.kind not in READERS:
        raise ValueError(f"unknown source kind {spec.kind!r}")
    C, R = READERS[spec.kind]
    try:
        rcfg = from_dict(C, {"root": spec.root, **dict(spec.options), "exclude": list(spec.exclude)})
    except ConfigError as e:
        raise ConfigError(f"{spec.section}: {e}") from None
    return R(rcfg)


def new_state(spec: SourceSpec, item_id: str) -> dict:
    """The initial state of a unit (what the enumerate stage emits)."""
    return {
        "unit_id": unit_id_for(spec.origin.replace("/", "-"), item_id),
        "kind": spec.kind,
        "origin": spec.origin,
        "item_id": item_id,
        "spec": {"kind": spec.kind, "root": spec.root, "section": spec.section,
                 "max_items": spec.max_items, "options": [list(kv) for kv in spec.options],
                 "exclude": list(spec.exclude)},
        "clip": spec.clip,          # clip geometry for this unit (ClipConfig fields)
        "status": "ok",             # ok | quarantined
        "attempts": 1,
        "quarantine": [],           # rows: item, source, stage, reason, attempts
        "episode": None,            # filled by cut
        "windows": [],              # candidate windows (cut), labelled (label)
        "selected": [],             # chosen windows (balance)
        "clips": [],                # keys written to staging (encode)
        "balance": {},              # counts before/after (balance)
        "timings_s": {},            # stage -> seconds spent on this unit
        "written": None,            # commit summary (write)
    }


def spec_from_state(state: dict) -> SourceSpec:
    s = state["spec"]
    return SourceSpec(s["kind"], s["root"], s["section"], s["max_items"], tuple(tuple(kv) for kv in s["options"]),
                      exclude=tuple(s.get("exclude", ())))   # the stages' readers exclude OUT too (CARLA results)


def clip_of(state: dict) -> ClipConfig:
    """The unit's clip geometry (top-level ``clip`` or its source's override)."""
    return from_dict(ClipConfig, state["clip"])


def dumps(state: dict) -> str:
    return json.dumps(state, separators=(",", ":"))


def loads(text: str) -> dict:
    return json.loads(text)
