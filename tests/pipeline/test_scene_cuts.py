"""Scene cuts (resim/labeling/cuts.py): an edited video from two real dashcam clips joined by a hard cut goes through
`resim pipeline run` with the OpenDV-style source; the cut is found within one frame, no clip spans it, and the
windows across it are recorded as dropped. The detector itself: hard cuts, fades and dissolves of the labelled
set are found, and continuous driving gives none."""
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from resim.cli import main
from resim.labeling.config import CutConfig
from resim.labeling.cut_set import KINDS, build_cut_video, score
from resim.labeling.cuts import CutDetector, detect_cuts

from .conftest import FAST, REPO


@pytest.fixture(scope="module")
def dashcam() -> list[np.ndarray]:
    """The two real clips (RGB, 25 fps) at 256 x 144, the labeler's working size."""
    d = Path(os.environ.get("RESIM_SHARED_DIR", REPO.parent / "shared")) / "data" / "dashcam"
    if not d.is_dir():
        pytest.skip(f"{d} is absent (real dashcam clips live in ../shared, which a user's clone has none of)")
    out = []
    for name in ("solidWhiteRight.mp4", "challenge.mp4"):
        cap = cv2.VideoCapture(str(d / name))
        frames = []
        while True:
            ok, f = cap.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(cv2.resize(f, (256, 144), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB))
        out.append(np.stack(frames))
    return out


# measured on held-out seeds at 10 Hz (docs/pipeline.md "Scene cuts"): hard cuts and fades 1.00, dissolves 0.78
MIN_RECALL = {"hard": 5 / 6, "fade": 5 / 6, "dissolve": 3 / 6}


def _at_10_hz(video: np.ndarray) -> np.ndarray:
    """Source-frame indices of a 25-fps video resampled to 10 Hz as the OpenDV reader does (nearest frame)."""
    return np.minimum(np.round(np.arange(int(len(video) / 2.5)) * 2.5).astype(int), len(video) - 1)


@pytest.mark.parametrize("kind", KINDS)
def test_the_default_detector_finds_each_kind_of_transition(dashcam, kind):
    video, bounds = build_cut_video(dashcam, kind, num_cuts=6, seed=100)
    idx = _at_10_hz(video)
    found = [int(idx[c]) for c in detect_cuts(video[idx], 10.0, CutConfig())]
    s = score(found, bounds, tolerance_frames=3)           # one 10-Hz frame is 2.5 source frames
    assert s["recall"] >= MIN_RECALL[kind] and s["fp"] == 0, s


def test_continuous_driving_has_no_cut_and_streaming_equals_batch(dashcam):
    for clip in dashcam:
        assert detect_cuts(clip[_at_10_hz(clip)], 10.0, CutConfig()) == []
    video, bounds = build_cut_video(dashcam, "hard", num_cuts=4, seed=101)
    video = video[_at_10_hz(video)]
    det = CutDetector(CutConfig(), 10.0)
    for f in video:
        det.push(f)
    assert det.finish() == detect_cuts(video, 10.0, CutConfig()) and len(det.finish()) == 4
    assert detect_cuts(video, 10.0, CutConfig(method="none")) == []


def _write(path: Path, frames: np.ndarray, fps: float) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (frames.shape[2], frames.shape[1]))
    for f in frames:
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()


def _run(tmp_path, root, name, *extra):
    out = tmp_path / name
    args = ["pipeline", "run", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(out), "--no-progress",
            "--set", "sources.synthetic.root=null", "--set", f"sources.opendv.root={root}",
            "--set", "sources.opendv.start_discard_s=0", "--set", "sources.opendv.end_discard_s=0",
            "--set", "sources.opendv.min_height_px=32", "--set", "ray.executor=local", "--set", "labels.prefer=flow",
            *[a for kv in FAST if not kv.startswith("ray.") for a in ("--set", kv)], *extra]
    assert main(args) == 0
    return out


def _starts(out):
    """{clip start (10-Hz frame): meta} of every written clip."""
    from resim.shards.reader import iter_samples

    return {s["meta.json"]["start_frame"]: s["meta.json"] for s in iter_samples(out, decode_video=False,
                                                                                   attach_prompts=False)}


def test_an_edited_drive_with_a_cut_and_a_stop_is_curated(dashcam, tmp_path):
    """The issue's video: clip A, hard cut, clip B, 6 s frozen (the car stands), A again (a second cut)."""
    a, b = dashcam
    root = tmp_path / "videos"
    (root / "edited").mkdir(parents=True)
    # A's second copy starts on the clip grid (a multiple of the 2-s stride): a re-used segment whose windows
    # line up with the first copy's, which is what a per-window signature finds (see docs/pipeline.md)
    b = b[:len(b) - (len(a) + len(b) + 120) % 40]
    frozen = np.repeat(b[-1:], 120, axis=0)                           # 6 s at 20 fps: the car stands
    video = np.concatenate([a, b, frozen, a])
    # written at 20 fps; the OpenDV reader resamples to 10 Hz (every 2nd frame), the rate the stages see
    _write(root / "edited" / "drive.mp4", video, 20.0)
    (root / "videos.csv").write_text("video_id,start_discard_s,end_discard_s\nedited/drive,0,0\n")
    cuts = [-(-len(a) // 2), -(-(len(a) + len(b) + len(frozen)) // 2)]     # 10-Hz frames starting a new shot
    still = (-(-(len(a) + len(b)) // 2), (len(a) + len(b) + len(frozen)) // 2)   # [first, end) of the stop

    out = _run(tmp_path, root, "out", "--set", "clip.stride_frames=10", "--set", "labels.cuts.method=flow")
    marker = next(iter(json.loads(p.read_text()) for p in (out / "commits").glob("*.json")))
    found = [c["frame"] for c in marker["cuts"]]
    assert len(found) == 2 and all(abs(f - c) <= 1 for f, c in zip(found, cuts)), (found, cuts)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["scene_cuts"]["cuts"] == 2 and stats["scene_cuts"]["windows_dropped"] >= 1

    clips = _starts(out)
    assert clips and not [s for s in clips for c in found if s < c <= s + 48], "a clip spans a cut"
    inside = {s: m for s, m in clips.items() if still[0] <= s and s + 48 < still[1]}
    assert inside, "no clip inside the stop"
    for s, m in inside.items():               # the stop: tagged, forward, never over-sampled
        assert m["stopped"] is True and m["ego_motion_pct_s"] < 1.0 and not m["is_turning"], m
        assert m["balance_weight"] == 1.0 and s % 10 == 0
    moving = [m for s, m in clips.items() if s + 48 < still[0]]
    assert moving and all(m["stopped"] is False and m["ego_motion_pct_s"] > 2.0 for m in moving)
    from resim.shards.manifest import read_manifest
    man = read_manifest(out).to_pydict()
    tagged = sorted(m["key"] for m in clips.values() if m["stopped"])   # inside, or mostly inside, the stop
    assert sorted(k for k, st in zip(man["key"], man["stopped"]) if st) == tagged
    assert {m["key"] for m in inside.values()} <= set(tagged)
    # A again at the end: its clips are near-duplicates of the first A's (a few frames apart on the 10-Hz
    # grid); the dedup pass keeps the first of each group and the training loader skips the others
    dups = pq.read_table(out / "dedup" / "duplicates.parquet").to_pylist()
    late_a = {m["key"] for s, m in clips.items() if s >= cuts[1]}
    first_a = {m["key"] for s, m in clips.items() if s + 48 < cuts[0]}
    assert dups and {d["key"] for d in dups} <= late_a and {d["duplicate_of"] for d in dups} <= first_a, dups
    assert stats["duplicates"]["clips_left_out"] == len(dups)
    from resim.train.config import DataConfig
    from resim.train.data import StreamLoader
    from resim.config import from_dict
    loader = StreamLoader(from_dict(DataConfig, {"shards": str(out), "batch_size_per_gpu": 1, "num_workers": 0,
                                                 "samples_per_epoch": 3 * len(clips)}), verbose=False)
    seen = {k for b in loader for k in b.keys}
    assert seen and not seen & {d["key"] for d in dups} and seen <= set(m["key"] for m in clips.values())
    # per-clip quality columns (resim/pipeline/clip_quality.py): the frozen frames' edges stand still and the flow's fit
    # finds nothing to hold; driving clips of the same video have few static edges and a fully kept fit
    for m in clips.values():
        assert 90 < m["luma_mean_8bit"] < 140 and 30 < m["luma_std_8bit"] < 60 and m["sharpness_lapvar"] > 500, m
    assert min(m["static_edge_frac"] for m in inside.values()) > 2 * max(m["static_edge_frac"] for m in moving)
    assert max(m["flow_quality"] for m in inside.values()) < 0.5 <= min(m["flow_quality"] for m in moving)
    # the curation report: the funnel adds up, and the dropped examples are drawn
    f = stats["curation"]
    assert abs(f["hours_in"] * 3600 - len(video) / 20.0) < 1.0 and f["units_quarantined"] == 0
    assert f["windows_dropped"] == {"scene cut": stats["scene_cuts"]["windows_dropped"]}
    assert f["clips_for_training"] == len(clips) - len(dups) and f["candidate_windows"] >= len(clips) + 48
    assert (out / "curation.png").stat().st_size > 10_000
    # the same run without cut detection writes clips across the cut: what the detector is for; with a quality
    # filter on static edges (in the config, with its unit) the frozen segment's windows are dropped before the VAE
    out_off = _run(tmp_path, root, "off", "--set", "clip.stride_frames=10", "--set", "labels.cuts.method=none",
                   "--set", "quality.max_static_edge_frac=0.1")
    off = _starts(out_off)
    assert [s for s in off if s < cuts[0] <= s + 48]
    assert not [s for s in off if still[0] <= s and s + 48 < still[1]], "a frozen clip passed the filter"
    assert all(m["static_edge_frac"] <= 0.1 for m in off.values())
    rows = [r for r in pq.read_table(out_off / "quarantine").to_pylist() if r["stage"] == "encode"]
    assert rows and all(r["reason"].startswith("low quality: static_edge_frac") for r in rows), rows
    f = json.loads((out_off / "stats.json").read_text())["curation"]
    assert f["windows_dropped"]["low quality: static_edge_frac"] == len(rows)
    # and with labels.still.policy=drop the stop is left out, with its rows
    dropped = _run(tmp_path, root, "drop", "--set", "clip.stride_frames=10", "--set", "labels.still.policy=drop")
    assert not [m for m in _starts(dropped).values() if m["stopped"]]
    assert json.loads((dropped / "stats.json").read_text())["standing_still"]["windows_dropped"] >= len(inside)
