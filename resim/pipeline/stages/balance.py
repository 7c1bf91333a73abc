"""Stage 4: ReSim's turn balance — turning segments are sampled ``turn_factor`` x more densely.

Candidates lie on the fine grid (``clip.stride_frames / turn_factor``). Straight-driving windows are
kept on the coarse grid only (every ``stride_frames``); turning windows are kept on the fine grid, so a
turning stretch of the source yields ``turn_factor`` x as many (distinct, overlapping) windows as the
same stretch of straight driving. Nothing is copied: every kept window has its own start frame, its
own frames and its own key.

Counts recorded per unit (summed into stats.json / the report):

* ``before``: windows on the coarse grid = what an unbalanced run at ``stride_frames`` would write;
  its turning share is the share of source time spent turning;
* ``after``: windows kept; turning share after = f*s / (f*s + 1 - s) for share s and factor f.
"""
from __future__ import annotations

from resim.pipeline.stages.base import Stage
from resim.pipeline.units import clip_of


def select_windows(windows: list[dict], stride: int, factor: int, enabled: bool) -> tuple[list[dict], dict]:
    """Pure selection: returns (kept windows with ``balance_weight``, counts before/after)."""
    kept = []
    before = {"clips": 0, "turning": 0}
    for w in windows:
        coarse = w["start"] % stride == 0
        if coarse:
            before["clips"] += 1
            before["turning"] += int(w["is_turning"])
        if coarse or (enabled and w["is_turning"]):
            kept.append({**w, "balance_weight": float(factor) if (enabled and w["is_turning"]) else 1.0})
    after = {"clips": len(kept), "turning": sum(int(w["is_turning"]) for w in kept)}
    return kept, {"before": before, "after": after}


class BalanceStage(Stage):
    name = "balance"

    def process(self, state: dict) -> None:
        b = self.cfg.balance
        kept, counts = select_windows(state["windows"], clip_of(state).stride_frames, b.turn_factor, b.enabled)
        state["selected"] = kept
        state["balance"] = counts
        state["windows"] = []          # candidates are no longer needed: keep rows small
