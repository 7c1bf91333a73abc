"""Stage 7: write a unit's clips into shards, its quarantine rows, and finally its commit marker.

Commit protocol (what makes ``kill -9`` at any moment safe):

1. remove whatever an earlier, interrupted attempt left under this unit's prefix (index first, so
   those shards count as uncommitted at once; then manifests and tars);
2. ``ShardWriter(prefix=unit_id)`` writes ``shards/<unit_id>-NNNNN.tar`` (tmp name → fsync → rename),
   then the manifest and index of each shard;
3. ``quarantine/<unit_id>.parquet`` (atomic);
4. ``commits/<unit_id>.json`` (atomic, last): the unit is done. A rerun skips units with a marker and
   redoes every other unit from scratch — with deterministic keys, labels and latent noise it rewrites
   the same samples under the same names, so the final set equals an uninterrupted run's.
"""
from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np

from resim.pipeline import quarantine, resume
from resim.pipeline.stages.base import Stage
from resim.pipeline.stages.encode import data_config_hash
from resim.pipeline.units import dumps, loads
from resim.shards.writer import ShardWriter


def remove_unit_files(out: Path, unit_id: str) -> int:
    """Delete every index/manifest/shard file of ``unit_id``'s prefix (an uncommitted unit's leftovers)."""
    own = re.compile(rf"^\.?{re.escape(unit_id)}-\d{{5}}\.(tar|json|parquet)")
    n = 0
    for sub in ("index", "manifest", "shards"):
        d = out / sub
        if not d.is_dir():
            continue
        for p in d.iterdir():
            if own.match(p.name):
                p.unlink(missing_ok=True)
                n += 1
    return n


class WriteStage(Stage):
    name = "write"
    writes_out = True         # it reads only the unit's staging files and writes OUT: no error here is the unit's

    def __init__(self, cfg, progress=None):
        super().__init__(cfg, progress)
        self.out = Path(self.cfg.out)
        self.config_hash = data_config_hash(self.cfg)

    def wants(self, state: dict) -> bool:
        return True   # quarantined units are committed too (with their rows, and no shards)

    def __call__(self, batch: dict) -> dict:
        """Rows leaving the pipeline carry only the unit's summary (the driver needs no more)."""
        out = [dumps(resume.summary(self.run_one(loads(s)))) for s in batch["unit"]]
        self._mark(len(out))
        return {"unit": np.array(out, dtype=object)}

    def read_sample(self, stage_dir: Path, key: str) -> dict:
        sample = {"__key__": key, "meta.json": json.loads((stage_dir / f"{key}.meta.json").read_text()),
                  "latent.npy": np.load(stage_dir / f"{key}.latent.npy", allow_pickle=False),
                  "frames.mp4": (stage_dir / f"{key}.frames.mp4").read_bytes()}
        traj = stage_dir / f"{key}.traj.npy"
        if traj.exists():
            sample["traj.npy"] = np.load(traj, allow_pickle=False)
        return sample

    def process(self, state: dict) -> None:
        t0 = time.perf_counter()
        uid = state["unit_id"]
        remove_unit_files(self.out, uid)
        try:
            self._write(state, t0)
        except BaseException:
            try:       # an uncommitted unit leaves nothing half-written behind (a rerun would remove it too)
                remove_unit_files(self.out, uid)
            except OSError:
                pass
            raise
        if state.get("staging"):
            shutil.rmtree(state["staging"], ignore_errors=True)

    def _write(self, state: dict, t0: float) -> None:
        uid = state["unit_id"]
        shards: list[dict] = []
        keys = state["clips"] if state["status"] == "ok" else []
        if keys:
            stage_dir = Path(state["staging"])
            sh = self.cfg.shards
            with ShardWriter(self.out, uid, max_samples_per_shard=sh.max_samples_per_shard,
                             max_bytes_per_shard=sh.max_bytes_per_shard, config_hash=self.config_hash,
                             overwrite=True) as w:
                for key in keys:
                    w.write(self.read_sample(stage_dir, key))
            shards = [{"name": i.name, "num_samples": int(i.num_samples)} for i in w.close()]
        quarantine.write_rows(self.out, uid, state["quarantine"])
        state["written"] = {"shards": shards, "num_samples": len(keys)}
        state["timings_s"]["write"] = state["timings_s"].get("write", 0.0) + time.perf_counter() - t0
        resume.write_marker(self.out, state)
        state["timings_s"]["write"] -= time.perf_counter() - t0    # run_one adds the whole stage time back
