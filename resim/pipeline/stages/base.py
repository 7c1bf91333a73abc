"""What every pipeline stage shares: a callable class over batches of unit states.

Ray Data calls ``Stage(cfg_dict)`` once per actor (heavy set-up: models, readers) and then
``stage(batch)`` for each batch of rows ``{"unit": array of JSON strings}``; the local executor calls the
same two things without Ray. ``__call__`` is pure with respect to the batch (it returns new rows);
side effects are confined to the unit's own staging folder and, in the writer, the unit's own shard
prefix — which is what makes a redo after a crash safe.

Bad input is turned into quarantine rows here, once, for all stages:

* ``SourceError`` (the readers' "this item is bad"): quarantined on the first attempt — retrying a
  corrupt file does not help;
* ``OSError`` (a file vanished, an NFS hiccup): retried ``quarantine.max_attempts`` times, then
  quarantined with the attempt count;
* an ``OSError`` that says OUT cannot be written (disk full, quota, read-only: ``OUTPUT_ERRNOS``), or any
  ``OSError`` of a stage that only touches OUT (``writes_out``: the writer), is the machine's problem, not
  the unit's: retried after a pause (a disk freed meanwhile lets the run go on), then :class:`OutputError`
  stops the run. Quarantining the unit would make a good unit look bad, and a unit without its commit
  marker must never be counted as done;
* anything else is our bug and propagates: the job fails loudly.
"""
from __future__ import annotations

import time

import numpy as np

from resim.media.files import OUTPUT_ERRNOS
from resim.pipeline import quarantine
from resim.pipeline.config import PipelineConfig, config_from_dict
from resim.pipeline.sources.episode import SourceError
from resim.pipeline.units import dumps, loads


def source_error_reason(e, item_id: str) -> str:
    """The quarantine reason of a reader's ``SourceError``: its reason, prefixed by the file/frame it
    named (``e.item``) unless that is just the unit's item id — the file/frame is what a user must fix."""
    return e.reason if e.item == item_id else f"{e.item}: {e.reason}"




class OutputError(RuntimeError):
    """OUT (or the temporary folder) cannot be written: the run stops with this one-line message. Units
    committed so far are kept; a rerun redoes the rest."""


class BadInput(Exception):
    """Raised by our own checks on input data (too short, too low-res, NaN poses...)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Stage:
    name = "stage"
    writes_out = False        # True: every I/O error of this stage is on OUT (see the module docstring)
    output_attempts = 4       # tries of a unit whose output was refused (pauses 2, 4, 8 s: a disk full for a
    output_pause_s = 2.0      # few seconds, e.g. while another job cleans up, costs a pause, not the run)

    def __init__(self, cfg: dict | PipelineConfig, progress=None):
        self.cfg = cfg if isinstance(cfg, PipelineConfig) else config_from_dict(cfg)
        self.progress = progress       # a ProgressBoard actor handle (Ray executor) or None

    # --- per unit --------------------------------------------------------------------------------
    def process(self, state: dict) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def wants(self, state: dict) -> bool:
        """Whether this stage has work for the unit (quarantined units pass straight through)."""
        return state["status"] == "ok"

    def run_one(self, state: dict) -> dict:
        if not self.wants(state):
            return state
        t0 = time.perf_counter()
        attempts = 0
        while True:
            attempts += 1
            try:
                self.process(state)
                break
            except SourceError as e:
                quarantine.quarantine_unit(state, self.name, source_error_reason(e, state["item_id"]),
                                           attempts=state["attempts"])
                break
            except BadInput as e:
                quarantine.quarantine_unit(state, self.name, e.reason, attempts=state["attempts"])
                break
            except OSError as e:
                if self.writes_out or e.errno in OUTPUT_ERRNOS:
                    if attempts < self.output_attempts:
                        time.sleep(self.output_pause_s * 2 ** (attempts - 1))
                        continue
                    raise OutputError(f"{self.name} of unit {state['unit_id']}: cannot write after {attempts} "
                                      f"attempts: {e}. Units committed so far are kept; free the space (or fix "
                                      f"the mount) and rerun the same command to complete the dataset") from None
                # transient I/O on the unit's input: retry, then quarantine with the count
                # state["attempts"] is the unit's total number of tries (this run's and, with
                # quarantine.retry_quarantined, earlier runs'): the marker and the row both report it
                if attempts < self.cfg.quarantine.max_attempts:
                    state["attempts"] += 1
                    continue
                quarantine.quarantine_unit(state, self.name, f"I/O error after {attempts} attempts: {e}",
                                           attempts=state["attempts"])
                break
        state["timings_s"][self.name] = state["timings_s"].get(self.name, 0.0) + time.perf_counter() - t0
        return state

    def _mark(self, n: int) -> None:
        if self.progress is not None and n:
            self.progress.mark.remote(self.name, n)   # fire and forget

    # --- per batch (what Ray Data calls) -----------------------------------------------------------
    def __call__(self, batch: dict) -> dict:
        out = [dumps(self.run_one(loads(s))) for s in batch["unit"]]
        self._mark(len(out))
        return {"unit": np.array(out, dtype=object)}


class Chain:
    """Several stages in one actor (``ray.fuse_cpu_stages``): one process, one set-up, no hops between them.

    Used for cut → label → balance, which are cheap to hand over but each cost an actor start-up
    (seconds: imports) if pooled separately; the encode and write pools stay separate so they scale
    on their own (GPU vs. I/O).
    """

    def __init__(self, cfg, stages: tuple = (), progress=None):
        self.stages = [cls(cfg, progress=progress) for cls in stages]
        self.name = "+".join(s.name for s in self.stages)

    def __call__(self, batch: dict) -> dict:
        states = [loads(s) for s in batch["unit"]]
        for stage in self.stages:
            states = [stage.run_one(st) for st in states]
            stage._mark(len(states))
        return {"unit": np.array([dumps(st) for st in states], dtype=object)}
