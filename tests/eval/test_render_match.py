"""lab/render_match.py: reading how far a video drove by re-rendering the synthetic world it shows."""
import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

from resim.pipeline.sources.synth.generate import generate, preset

SCRIPT = Path(__file__).resolve().parents[2] / "lab" / "render_match.py"


@pytest.fixture(scope="module")
def rm():
    spec = importlib.util.spec_from_file_location("render_match", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_world_is_rebuilt_as_it_was_written_and_renders_its_frames_again(rm, tmp_path):
    """The reader's premise: from a world's seed and config the episode, its drive and every frame come back exactly."""
    cfg = preset("tiny", episode_s=4.0, height_px=32, width_px=56)
    generate(tmp_path / "w", 3, seed=4, cfg=cfg, progress=False)
    wr = rm.WorldRebuild(tmp_path / "w")
    item = next(i for i, e in wr.by_item.items() if e["layout"]["reader"] == "carla")
    renderer, tr = wr.episode(item)
    assert np.array_equal(tr.poses[:, 0], wr.by_item[item]["x_m"])
    frames = np.stack([renderer.render(tr.poses[s], tr.t_s[s]) for s in (0, 20, 40)])
    # the frames the CARLA layout stored (JPEG; file k is simulation step k * reader_stride)
    stride = wr.by_item[item]["layout"]["reader_stride"]
    for f, s in zip(frames, (0, 20, 40)):
        stored = cv2.imread(str(tmp_path / "w" / "carla" / item / "camera" / "rgb_front" / f"{s // stride:05d}.jpg"))
        err = np.abs(stored[..., ::-1].astype(int) - rm.jpeg(f, cfg.jpeg_quality).astype(int)).mean()
        assert err < 1.0, err           # measured 0.0: the same JPEG round trip (a frame 1 s off: 13-17 levels)
    # the same episode rendered by a second rebuild: byte for byte (the renderer's textures come from the same stream)
    again, tr2 = rm.WorldRebuild(tmp_path / "w").episode(item)
    assert np.array_equal(frames, np.stack([again.render(tr2.poses[s], tr2.t_s[s]) for s in (0, 20, 40)]))


def test_path_poses_scale_the_distance_along_the_recorded_path(rm):
    t = np.arange(0, 10.01, 0.05)
    # a quarter circle of radius 20 m at 5 m/s, then straight on
    s = 5.0 * t
    ang = np.minimum(s / 20.0, np.pi / 2)
    x = np.where(s / 20.0 < np.pi / 2, 20 * np.sin(ang), 20 + 0 * s)
    y = np.where(s / 20.0 < np.pi / 2, 20 * (1 - np.cos(ang)), 20 + (s - 10 * np.pi))
    poses = np.stack([x, y, ang], 1)
    times = np.array([1.0, 2.0, 3.0])
    assert np.allclose(rm.path_poses(poses, t, 1.0, times, 1.0), poses[[20, 40, 60]], atol=1e-2)
    still = rm.path_poses(poses, t, 1.0, times, 0.0)
    assert np.allclose(still, poses[[20, 20, 20]], atol=1e-9)
    twice = rm.path_poses(poses, t, 1.0, times, 2.0)          # 2x the distance: where the car is at 1 + 2 (t - 1) s
    assert np.allclose(twice, poses[[20, 60, 100]], atol=0.05)
    past = rm.path_poses(poses, t, 9.0, np.array([10.0]), 2.4)   # past the episode's end: straight on
    assert past[0, 1] > poses[-1, 1] and abs(past[0, 0] - poses[-1, 0]) < 1e-6


def test_read_scale_finds_the_candidate_a_video_was_made_from(rm):
    rng = np.random.default_rng(0)
    k_grid = rm.K_GRID
    # candidates whose latents move smoothly with k (so the error curve is a bowl) and a video between two of them
    base, slope = rng.normal(size=(13, 4, 2, 3)), rng.normal(size=(13, 4, 2, 3))
    cand = np.stack([base + k * slope for k in k_grid])
    k, contrast, per_frame = rm.read_scale(base + 1.23 * slope, cand, 3)
    assert abs(k - 1.23) < 0.02 and contrast > 10 and np.allclose(per_frame, 1.23, atol=0.02)
    # the upper rows alone read the same; the history frames are never compared
    assert abs(rm.read_scale(base + 1.23 * slope, cand, 3, slice(0, 1))[0] - 1.23) < 0.02
    hist_changed = base + 1.23 * slope
    hist_changed[:3] += 100.0
    assert abs(rm.read_scale(hist_changed, cand, 3)[0] - 1.23) < 0.02


def test_summary_tells_an_idm_that_reads_the_motion_from_one_that_reads_the_scene(rm):
    # the IDMs' known answer: true renders of each clip at the given scales. A reader of the motion reads the
    # render's own distance (slope 1); a reader of the scene reads the expert's habitual distance whatever the
    # speed (slope 0) although it reads every recorded video right
    rng = np.random.default_rng(1)
    scales = [0.5, 1.0, 1.5]
    rec = rng.uniform(15, 35, size=8)
    rows = []
    for i, d in enumerate(rec):
        read = {"k": 1.0, "contrast": 5.0, "dist_m": d, "dist_m_upper": d, "dist_m_lower": d}
        rows.append({"clip": f"c{i}", "item_id": f"e{i}", "hazard": False, "recorded_dist_m": float(d),
                     "render_dist_m": {f"{k:g}": float(d * k * 0.98) for k in scales},
                     "recorded": read, "recorded_reencoded": read, **{f"given_{k:g}": read for k in scales}})
    def reads(f):
        return {"recorded_video": rec.tolist(), **{f"given_{k:g}": rec.tolist() for k in scales},
                **{f"render_{k:g}{s}": [f(r, k) for r in rows] for k in scales for s in ("", "_through_vae")}}
    s = rm.summarise(rows, scales, {"motion": reads(lambda r, k: r["render_dist_m"][f"{k:g}"] + 0.3),
                                    "scene": reads(lambda r, k: r["recorded_dist_m"] + 0.1 * k)})
    motion, scene = s["expert_drivers"]["idm motion"], s["expert_drivers"]["idm scene"]
    for name in ("on_render", "on_render_through_vae"):
        assert abs(motion[name]["within_clip_slope_median"] - 1.0) < 1e-6
        assert abs(scene[name]["within_clip_slope_median"]) < 0.05
    assert np.allclose(motion["on_render"]["render_dist_m_mean"], [np.mean(rec * k * 0.98) for k in scales], atol=0.01)
