"""`resim pipeline check` looks at a few of the configured videos: warnings for a run that would make nothing.

Two mistakes that the config alone cannot show, and that a run reports only as quarantine rows after it has
decoded everything: discards (``start_discard_s + end_discard_s``, or a ``videos.csv`` row) that leave less than
one clip of a video, and a ``min_height_px`` above every video (``opendv.yaml``'s 720 against 540p dashcams).
Only the first few files are probed (``resim.media.video_probe.probe``: one open and one decoded frame each), so the
check stays cheap on a root of thousands of videos. Warnings only: the config is valid either way.
"""
from __future__ import annotations

from pathlib import Path

from resim.media.video_probe import VideoError, probe
from resim.pipeline.config import PipelineConfig
from resim.pipeline.sources.episode import SourceError
from resim.pipeline.units import make_reader, source_specs

MAX_PROBED = 8          # files probed per source


def opendv_warnings(cfg: PipelineConfig, max_probed: int = MAX_PROBED) -> list[str]:
    """One line per problem found in the first ``max_probed`` videos of ``sources.opendv`` (none: [])."""
    warnings = []
    for spec in source_specs(cfg):
        if spec.section != "sources.opendv":   # the synthetic world is generated to fit its config
            continue
        key, reader, opts = spec.section, make_reader(spec), dict(spec.options)
        try:
            items = reader.list_items()
        except SourceError as e:
            warnings.append(f"{key}: {e.item}: {e.reason} (the run quarantines the whole source)")
            continue
        if spec.max_items is not None:
            items = items[:spec.max_items]
        if not items:
            exts = ", ".join(f"*.{x}" for x in reader.cfg.extensions)
            warnings.append(f"{key}: no video ({exts}) under {spec.root}: the run would make nothing")
            continue
        clip = spec.clip
        clip_frames = clip["num_history_frames"] + clip["num_future_frames"]
        clip_s = clip_frames / clip["fps_hz"]
        probed = items[:max_probed]
        heights: dict[str, int] = {}
        for item in probed:
            try:
                info = probe(Path(spec.root) / item)
            except VideoError as e:
                warnings.append(f"{key}: {item}: {e.reason} (it will be quarantined)")
                continue
            heights[item] = info.height_px
            if info.num_frames <= 0:          # length unknown (a raw stream): nothing to compare
                continue
            try:
                start_s, end_s = reader.discards_s(item)
            except SourceError as e:          # a bad videos.csv row for this video
                warnings.append(f"{key}: {item}: {e.item}: {e.reason}")
                continue
            duration_s = info.num_frames / info.fps_hz
            left_s = duration_s - start_s - end_s
            # the reader keeps floor(left_s * fps_hz) frames; a clip needs clip_frames of them
            if left_s * clip["fps_hz"] + 1e-9 < clip_frames:
                left = ("exceed it" if left_s <= 0
                        else f"leave {left_s:.1f} s, less than one {clip_s:g} s clip")
                warnings.append(
                    f"{key}: {item} lasts {duration_s:.1f} s and the discards (start {start_s:g} s + end {end_s:g} s) "
                    f"{left}: it gives no clip (lower {key}.start_discard_s / end_discard_s, or set them per video "
                    f"in videos.csv)")
        min_h = opts["min_height_px"]
        if heights and all(h < min_h for h in heights.values()):
            which = (f"all {len(heights)} probed videos (of {len(items)})" if len(items) > len(probed)
                     else f"all {len(heights)} videos" if len(heights) > 1 else "the only readable video")
            warnings.append(
                f"{key}: {which} {'are' if len(heights) > 1 else 'is'} lower than min_height_px {min_h} (heights "
                f"{', '.join(str(h) for h in sorted(set(heights.values())))} px): every one would be quarantined; "
                f"lower it, e.g. --set {key}.min_height_px={min(heights.values())}")
    return warnings
