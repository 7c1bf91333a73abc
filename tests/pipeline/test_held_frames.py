"""``clip.max_held_frames``: an episode shorter than one clip by at most that many frames gives one clip, its
last frame held (a CARLA / synthetic route ends ~2 s after a crash: without it the early-crash hazards give no
clip, and reward training, which reads only shards, would never see them).

* ``Episode.hold_last`` repeats the last frame, pose and command (speed 0) and says so in ``warnings``;
* through the whole pipeline (local executor): a route 9 frames short gives one clip at start 0 with its
  infraction score and a warning row; 0 (the default) and a bound below the shortfall quarantine it as before;
* the option is validated on load, and at its default leaves the data hash what it was before the option existed.
"""
import shutil

import numpy as np
import pytest

from resim.config import ConfigError, config_hash
from resim.pipeline import quarantine, resume, runner
from resim.pipeline.sources.episode import Episode
from resim.shards.reader import iter_samples
from resim.shards.video import decode_mp4

from .conftest import make_config


def _episode(n: int) -> Episode:
    def loader(a, b, size_hw):
        for i in range(a, b):
            yield np.full((2, 3, 3), i, dtype=np.uint8)
    poses = np.c_[np.arange(n, dtype=float), np.zeros(n), np.zeros(n)]
    return Episode(source="carla", item_id="r", fps_hz=10.0, num_frames=n, frame_size_hw=(2, 3), poses=poses,
                   speed_mps=np.ones(n), timestamps_s=np.arange(n) / 10.0, _loader=loader)


def test_hold_last_repeats_the_last_frame_pose_and_stops_the_ego():
    ep = _episode(5).hold_last(8)
    assert ep.num_frames == 8 and ep.held_frames == 3
    assert [int(f[0, 0, 0]) for f in ep.frames()] == [0, 1, 2, 3, 4, 4, 4, 4]
    assert [int(f[0, 0, 0]) for f in ep.frames(3, 7)] == [3, 4, 4, 4]
    assert [int(f[0, 0, 0]) for f in ep.frames(6, 8)] == [4, 4]            # a range inside the held part
    np.testing.assert_array_equal(ep.poses[:, 0], [0, 1, 2, 3, 4, 4, 4, 4])
    np.testing.assert_array_equal(ep.speed_mps, [1, 1, 1, 1, 1, 0, 0, 0])
    np.testing.assert_allclose(ep.timestamps_s, np.arange(8) / 10.0)
    assert "3 frame(s) appended holding the last frame" in ep.warnings[-1]
    same = _episode(5)
    assert same.hold_last(5) is same and same.hold_last(3) is same


def _carla_config(root, out, *overrides):
    return make_config(out, ["sources.synthetic.root=null", f"sources.carla.root={root}", "ray.executor=local",
                             "balance.enabled=false", *overrides])


@pytest.fixture
def short_route(tmp_path, synth_world):
    """A copy of the world's CARLA routes with the expert's cut to 40 frames (a clip is 49): (root, route)."""
    root = shutil.copytree(synth_world / "carla", tmp_path / "carla")
    route = next(p for p in sorted(root.iterdir()) if p.name.startswith("SynthExpert"))
    for i in range(40, len(list((route / "anno").iterdir()))):
        (route / "anno" / f"{i:05d}.json.gz").unlink()
        (route / "camera" / "rgb_front" / f"{i:05d}.jpg").unlink()
    return root, route.name


def _rows(out, item):
    return [r for r in quarantine.read_table(out) if r["item"] == item]


def test_a_route_short_of_one_clip_gives_one_clip_with_its_last_frame_held(short_route, tmp_path):
    root, item = short_route
    out = tmp_path / "held"
    runner.run(_carla_config(root, out, "clip.max_held_frames=9"))
    samples = [s for s in iter_samples(out, attach_prompts=False) if s["meta.json"]["item_id"] == item]
    assert len(samples) == 1
    meta = samples[0]["meta.json"]
    assert meta["start_frame"] == 0 and meta["num_frames"] == 49
    assert meta["infraction_score"] == 1.0 and meta["hazard"] is False       # the route's outcome reaches the shard
    frames = decode_mp4(samples[0]["frames.mp4"]).astype(int)
    assert len(frames) == 49
    moving = np.abs(frames[1:40] - frames[:39]).mean()
    held = np.abs(frames[40:] - frames[39]).mean()
    assert held < 0.2 * moving, (held, moving)             # frames 40..48 show frame 39 (up to mp4 coding)
    assert [r["status"] for r in _rows(out, item)] == ["warning"]
    (marker,) = [m for m in resume.read_markers(out).values() if m["item_id"] == item]
    assert marker["curation"]["used_s"] == marker["curation"]["covered_s"] == 4.0   # recorded footage, not held
    assert "9 frame(s) appended holding the last frame" in _rows(out, item)[0]["reason"]


@pytest.mark.parametrize("held, why", [(0, "too short: 40 frames at 10 Hz < 49 needed for one clip (4.9 s)"),
                                       (5, "9 missing > max_held_frames 5")])
def test_a_route_shorter_than_the_bound_is_still_quarantined(short_route, tmp_path, held, why):
    root, item = short_route
    out = tmp_path / f"held{held}"
    runner.run(_carla_config(root, out, f"clip.max_held_frames={held}"))
    assert all(s["meta.json"]["item_id"] != item for s in iter_samples(out, attach_prompts=False))
    (row,) = _rows(out, item)
    assert row["status"] == "quarantined" and why in row["reason"]
    if held == 0:       # the reason of the default is the one it always was
        assert row["reason"] == "too short: 40 frames at 10 Hz < 49 needed for one clip (4.9 s)"


@pytest.mark.parametrize("value", [-1, 49, 1.5])
def test_max_held_frames_is_validated_on_load(tmp_path, value):
    with pytest.raises(ConfigError, match="max_held_frames"):
        make_config(tmp_path / "o", [f"clip.max_held_frames={value}"])


def test_the_default_leaves_the_data_hash_as_it_was(tmp_path):
    from resim.pipeline.config import absolute_paths
    from resim.pipeline.stages.encode import data_config_hash
    from resim.config import to_dict

    cfg = make_config(tmp_path / "o", ["sources.carla.clip={stride_frames: 10}"])
    d = to_dict(absolute_paths(cfg))
    for c in (d["clip"], d["sources"]["carla"]["clip"], *d["sources"]["synthetic"]["clip"].values()):
        del c["max_held_frames"]                      # the config as it was before the field existed
    del d["sources"]["synthetic"]["fork_fraction"]    # (later fields, at their defaults: left out alike)
    del d["sources"]["synthetic"]["pace_fork_fraction"]
    before = config_hash({k: d[k] for k in ("sources", "clip", "labels", "balance", "quality", "encode", "shards")})
    assert data_config_hash(cfg) == before
    assert data_config_hash(make_config(tmp_path / "o", ["sources.carla.clip={stride_frames: 10, max_held_frames: 3}"])) \
        != before


def test_the_reward_config_loads_and_cuts_a_whole_synthetic_route_into_one_clip(tmp_path):
    from resim.pipeline.load import load_config

    from .conftest import REPO

    cfg = load_config(REPO / "configs/pipeline/carla-reward.yaml", [f"sources.carla.root={tmp_path}"],
                      out=tmp_path / "o")
    # a synthetic tiny route is 80 frames: one 81-frame clip (its last frame held once); a route ending 2 s
    # after an early crash (>= 33 frames) still gives one
    assert (cfg.clip.num_frames, cfg.clip.stride_frames, cfg.clip.max_held_frames) == (81, 80, 48)
    assert not cfg.balance.enabled
