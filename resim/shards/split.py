"""The dataset's train / held-out split: whole episodes on one side, written by the pipeline beside the manifest
(``DIR/split.json``) and read by every trainer and evaluator, which record it in their run.

An episode is a source item (``item_id``: a video, a log, a route): its overlapping clips on both sides would leak.
Its side is decided by a seeded hash of its id against ``heldout_fraction``, not by a count: a dataset that grows
(a resumed or extended pipeline run) never moves an episode from held-out into training, so a model trained
before the growth is still evaluated on episodes it never saw. The one exception is the top-up: a source with
fewer than ``min_heldout_episodes`` episodes under the threshold has its lowest-hash episodes held out to reach
it, a set that can change while the source is that small (``split.json`` lists them as ``topped_up``).

Per source: each source (opendv, navsim, carla, ...) is held out in the same share, and tops up on its own, taking
hazardous and clean drives (the hazard flag) in turn so that a small source's held-out episodes hold both, as
Video2Reward's evaluation needs. One episode of each source always trains.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from resim.config import ConfigError, from_dict, to_dict
from resim.shards import fsio
from resim.shards.errors import ShardReadError
from resim.shards.manifest import read_manifest

SPLIT_FILE = "split.json"


@dataclass
class SplitConfig:
    """The pipeline's ``split`` section."""

    heldout_fraction: float = 0.2     # of the episodes, by hash (so about, not exactly)
    seed: int = 0                     # another seed, another split of the same episodes
    min_heldout_episodes: int = 1     # per source of at least 2 episodes (topped up by lowest hash)

    def __post_init__(self):
        if not 0.0 < self.heldout_fraction < 1.0:
            raise ConfigError(f"split.heldout_fraction must be in (0, 1), got {self.heldout_fraction}")
        if self.min_heldout_episodes < 0:
            raise ConfigError(f"split.min_heldout_episodes must be >= 0, got {self.min_heldout_episodes}")


def episode_hash(item_id: str, seed: int) -> float:
    """A uniform number in [0, 1) from (seed, item_id): the episode is held out when it is below the fraction."""
    h = hashlib.sha256(f"{seed}\0{item_id}".encode()).digest()
    return int.from_bytes(h[:8], "big") / 2.0 ** 64


def assign(episodes: dict[str, tuple], cfg: SplitConfig) -> tuple[set[str], set[str]]:
    """(held-out episodes, those of them topped up) for ``episodes`` (item_id -> (source, hazard))."""
    held, topped = set(), set()
    for source in sorted({k[0] for k in episodes.values()}, key=repr):
        eps = sorted((e for e, k in episodes.items() if k[0] == source), key=lambda e: episode_hash(e, cfg.seed))
        if len(eps) < 2:
            continue
        chosen = [e for e in eps if episode_hash(e, cfg.seed) < cfg.heldout_fraction][:len(eps) - 1]
        want = min(len(eps) - 1, cfg.min_heldout_episodes)      # one episode of each source always trains
        rest = [e for e in eps if e not in chosen]
        while len(chosen) < want:
            # the lowest-hash episode of the hazard class held out least so far: a small source's held-out
            # episodes are then hazardous and clean alike, which Video2Reward's evaluation needs
            n_class = {h: sum(episodes[c][1] == h for c in chosen) for h in {episodes[e][1] for e in rest}}
            pick = min(rest, key=lambda e: (n_class[episodes[e][1]], episode_hash(e, cfg.seed)))
            rest.remove(pick)
            chosen.append(pick)
            topped.add(pick)
        held.update(chosen)
    return held, topped


@dataclass(frozen=True)
class DatasetSplit:
    """The split of one dataset. ``origin`` says where it came from: its ``split.json``, or computed on read
    from the manifest for a dataset written before the split existed."""

    config: SplitConfig
    heldout: frozenset[str]
    train: frozenset[str]
    topped_up: frozenset[str]
    origin: str

    def side(self, item_id: str) -> str:
        if item_id in self.heldout:
            return "heldout"
        if item_id in self.train:
            return "train"
        raise ShardReadError(f"episode {item_id!r} is in neither side of the split ({self.origin}): the dataset "
                             "changed after its split was written; rerun `resim shards split DIR`")

    def summary(self) -> dict:
        """Where the split comes from, its config, its sizes and a digest of the held-out list."""
        digest = hashlib.sha256("\n".join(sorted(self.heldout)).encode()).hexdigest()[:16]
        return {"origin": self.origin, **to_dict(self.config), "episodes_train": len(self.train),
                "episodes_heldout": len(self.heldout), "heldout_sha256_16": digest}

    def record(self, side: str) -> dict:
        """What a run stores about the split it used: the side it read, and :meth:`summary`."""
        return {"side": side, **self.summary()}


def read_all(roots) -> DatasetSplit:
    """One split over several datasets (each its own :func:`read`); an episode on both sides is an error."""
    parts = [read(r) for r in roots]
    if len(parts) == 1:
        return parts[0]
    held = frozenset().union(*(p.heldout for p in parts))
    train = frozenset().union(*(p.train for p in parts))
    both = held & train
    if both:
        raise ShardReadError(f"episode {sorted(both)[0]!r} is held out in one of {', '.join(map(str, roots))} and "
                             "trained on in another: give them one split (`resim shards split DIR --seed S`)")
    return DatasetSplit(parts[0].config, held, train, frozenset().union(*(p.topped_up for p in parts)),
                        "; ".join(p.origin for p in parts))


def _episodes(t) -> dict[str, tuple[str, bool | None]]:
    """item_id -> (source, hazard flag) of manifest table ``t``: hazard true if any clip of the episode is
    hazardous, false if any is not, else none."""
    out: dict[str, tuple[str, bool | None]] = {}
    for item, src, hz in zip(t["item_id"].to_pylist(), t["source"].to_pylist(), t["hazard"].to_pylist()):
        prev = out.get(item, (src, None))[1]
        out[item] = (src, True if (prev is True or hz is True) else (False if (prev is False or hz is False) else None))
    return out


def of_episodes(episodes: dict[str, tuple], cfg: SplitConfig, origin: str) -> DatasetSplit:
    """The split of ``episodes`` (item_id -> (source, hazard)) by :func:`assign`."""
    held, topped = assign(episodes, cfg)
    return DatasetSplit(cfg, frozenset(held), frozenset(set(episodes) - held), frozenset(topped), origin)


def compute(root: str | Path, cfg: SplitConfig, origin: str, manifest=None) -> DatasetSplit:
    """The split of ``root``'s committed episodes (``manifest``: its ``read_manifest`` table, if already read)."""
    return of_episodes(_episodes(read_manifest(root) if manifest is None else manifest), cfg, origin)


def write(root: str | Path, cfg: SplitConfig) -> DatasetSplit:
    """Compute the split of ``root``'s committed episodes and write ``root/split.json`` (atomically)."""
    path = Path(root) / SPLIT_FILE
    s = compute(root, cfg, str(path))
    body = {"config": to_dict(cfg), "rule": "held out: sha256(seed, item_id) < heldout_fraction; each source topped up "
            "to min_heldout_episodes by lowest hash, hazard classes in turn; one episode of each source trains", "episodes_train": len(s.train),
            "episodes_heldout": len(s.heldout), "heldout": sorted(s.heldout), "topped_up": sorted(s.topped_up),
            "train": sorted(s.train)}
    fsio.atomic_write_bytes(path, (json.dumps(body, indent=1) + "\n").encode())
    return s


def read(root: str | Path, manifest=None) -> DatasetSplit:
    """The split of dataset ``root``: its ``split.json``; without one (a dataset older than the split), the
    default split computed from the manifest (``origin`` says so; callers show it in their summary). A ``split.json`` that does not list every
    episode of the manifest, or that is malformed, is a ``ShardReadError`` naming the file. ``manifest``: the
    dataset's ``read_manifest`` table, where the caller has it already."""
    root = Path(root)
    path = root / SPLIT_FILE
    if not path.is_file():
        origin = f"the default split, computed on read (no {path}: `resim shards split {root}` writes it)"
        return compute(root, SplitConfig(), origin, manifest=manifest)
    try:
        body = json.loads(path.read_text())
        cfg = from_dict(SplitConfig, body["config"], prefix="split.")
        held, train = frozenset(body["heldout"]), frozenset(body["train"])
        topped = frozenset(body.get("topped_up", []))
    except (OSError, ValueError, KeyError, TypeError, ConfigError) as e:
        raise ShardReadError(f"{path}: not a split file ({e}); `resim shards split {root}` rewrites it") from None
    missing = set(_episodes(read_manifest(root) if manifest is None else manifest)) - held - train
    if missing:
        raise ShardReadError(f"{path}: {len(missing)} episode(s) of the manifest are in neither side (e.g. "
                             f"{sorted(missing)[0]!r}): the dataset grew after its split was written; rerun "
                             f"`resim pipeline run` or `resim shards split {root}`")
    return DatasetSplit(cfg, held, train, topped, str(path))
