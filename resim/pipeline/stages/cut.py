"""Stage 2: open a unit's episode, check it is usable, and cut it into candidate clip windows.

Cutting is index arithmetic: a window is ``[start, start + num_frames)`` in clip-rate frames. Candidates
lie on the *fine* grid (``clip.stride_frames / balance.turn_factor``) so the balance stage can keep
every turning window there and only the coarse-grid ones elsewhere. Pixels are decoded later by the
stages that need them, each at its own size (flow: tiny; VAE: the training resolution).

Quarantined here (bad input, not our bug): unreadable / zero-byte / truncated items (the reader's
``SourceError``), a frame rate that cannot be brought to ``clip.fps_hz``, fewer frames than one clip,
frames lower than ``sources.opendv.min_height_px`` (OpenDV) or smaller than the VAE input. An episode short of
one clip by at most ``clip.max_held_frames`` gives one clip with its last frame held instead. The episode's
``warnings`` (defects the reader repaired, a route without outcome) become ``warning`` rows of the
quarantine table: the unit goes on, and the caveat is saved with the dataset.
"""
from __future__ import annotations

from resim.media.frames import rate_step
from resim.pipeline import quarantine
from resim.pipeline.stages.base import BadInput, Stage
from resim.pipeline.units import clip_of, make_reader, spec_from_state


class CutStage(Stage):
    name = "cut"

    def __init__(self, cfg, progress=None):
        super().__init__(cfg, progress)
        self._readers: dict = {}

    def reader(self, state: dict):
        spec = spec_from_state(state)
        if spec not in self._readers:
            self._readers[spec] = make_reader(spec)
        return self._readers[spec]

    def open(self, state: dict):
        """The unit's episode; one shorter than a clip by at most ``clip.max_held_frames`` frames is lengthened
        to one clip by holding its last frame (``Episode.hold_last``), the same way in every stage."""
        ep = self.reader(state).open(state["item_id"])
        clip = clip_of(state)
        step = rate_step(ep.fps_hz, clip.fps_hz) if clip.max_held_frames else None
        if step is not None and ep.num_frames > 0:
            short = clip.num_frames - ((ep.num_frames - 1) // step + 1)      # clip-rate frames missing
            if 0 < short <= clip.max_held_frames:
                ep = ep.hold_last((clip.num_frames - 1) * step + 1)
        return ep

    def process(self, state: dict) -> None:
        cfg, clip = self.cfg, clip_of(state)
        ep = self.open(state)
        if (ep.source, ep.item_id) != (state["kind"], state["item_id"]):
            # sample keys are make_key(ep.source, ep.item_id, start); enumerate checked them for collisions
            # as (kind, item_id), so a reader must not rename its items (our bug, fail loudly)
            raise RuntimeError(f"{state['item_id']}: the {state['kind']} reader returned an episode of "
                               f"({ep.source!r}, {ep.item_id!r})")
        step = rate_step(ep.fps_hz, clip.fps_hz)
        if step is None:
            raise BadInput(f"frame rate {ep.fps_hz:g} Hz cannot be brought to the clip rate {clip.fps_hz:g} Hz "
                           "by integer subsampling (set a per-source `clip` in the config to cut clips at the "
                           "source's own rate)")
        n = (ep.num_frames - 1) // step + 1 if ep.num_frames > 0 else 0     # clip-rate frames available
        N = clip.num_frames
        if n < N:
            held = (f"; {N - n} missing > max_held_frames {clip.max_held_frames} that may hold the last frame"
                    if clip.max_held_frames else "")
            raise BadInput(f"too short: {n} frames at {clip.fps_hz:g} Hz < {N} needed for one clip "
                           f"({N / clip.fps_hz:g} s){held}")
        h, w = ep.frame_size_hw
        if state["kind"] == "opendv" and state["spec"]["section"] == "sources.opendv" \
                and h < cfg.sources.opendv.min_height_px:
            raise BadInput(f"too low resolution: {h} px high < sources.opendv.min_height_px "
                           f"{cfg.sources.opendv.min_height_px}")
        if h < cfg.encode.height_px // 2 or w < cfg.encode.width_px // 2:
            raise BadInput(f"too low resolution: {h}x{w} px for encode {cfg.encode.height_px}x{cfg.encode.width_px} "
                           "(more than 2x upscaling)")
        fine = cfg.fine_stride_frames(clip)
        starts = list(range(0, n - N + 1, fine))
        outcome = ep.outcome
        state["episode"] = {
            "source": ep.source,
            "item_id": ep.item_id,
            "fps_hz": float(ep.fps_hz),
            "step": step,
            "num_frames": n,
            "frame_size_hw": [int(h), int(w)],
            "has_poses": ep.poses is not None,
            "hazard": None if outcome is None else bool(outcome.hazard),
            "infraction_score": None if outcome is None else float(outcome.infraction_score),
            "infractions": None if outcome is None else [str(x) for x in outcome.infractions],
            "warnings": [str(x) for x in getattr(ep, "warnings", [])],
            # clip-rate frames at the end that only hold the last recorded one (clip.max_held_frames)
            "held_frames": n - ((ep.num_frames - ep.held_frames - 1) // step + 1) if ep.held_frames else 0,
        }
        state["windows"] = [{"start": s} for s in starts]
        used_s = (ep.num_frames - ep.held_frames) / ep.fps_hz     # recorded frames only, not held ones
        # the curation funnel (resim/pipeline/curation.py): hours in, hours after the reader's discards, candidates
        state["curation"] = {"source_s": round(float(ep.source_duration_s or used_s), 3), "used_s": round(used_s, 3),
                             "windows": len(starts)}
        for w in state["episode"]["warnings"]:   # last, so a retried or failed cut adds none
            quarantine.warn(state, self.name, w)
