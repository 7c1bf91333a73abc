import math

import numpy as np
import pytest

from resim.pipeline.sources.episode import SourceError, scan_items
from resim.pipeline.sources.navsim import NavsimConfig, NavsimReader, quaternion_yaw, yaw_quaternion

GOOD = "2021.05.12.22.00.38_veh-35_01008_01518"


def test_reads_log_in_real_layout(navsim_root):
    r = NavsimReader(NavsimConfig(root=navsim_root, split="mini"))
    ep = r.open(GOOD)
    assert ep.source == "navsim" and ep.fps_hz == 2.0 and ep.num_frames == 6
    assert np.allclose(ep.poses[:, 2], 0.1 * np.arange(6))
    assert np.allclose(ep.poses[:, 0], 2.0 * np.arange(6)) and np.allclose(ep.poses[:, 1], 0.5 * np.arange(6) ** 2)
    assert np.allclose(ep.speed_mps, 5.0) and np.allclose(ep.timestamps_s, 0.5 * np.arange(6))
    assert ep.driving_command.shape == (6, 4) and (ep.driving_command[:, 1] == 1).all()
    frames = list(ep.frames(size_hw=(24, 40)))
    assert len(frames) == 6 and frames[0].shape == (24, 40, 3)
    assert r.open("good_protocol4").num_frames == 5


def test_quaternion_yaw_matches_closed_form():
    for yaw in np.linspace(-3, 3, 13):
        assert math.isclose(quaternion_yaw(yaw_quaternion(yaw)), yaw, abs_tol=1e-12)


def test_broken_logs_reported_with_item_and_reason(navsim_root):
    good, problems = scan_items(NavsimReader(NavsimConfig(root=navsim_root, split="mini")))
    assert sorted(good) == sorted([GOOD, "good_protocol4"])
    by = {next(b for b in ("missing_image", "missing_frame", "evil_class", "missing_key", "truncated")
               if b in e.item or b in e.reason): e for e in problems}
    assert set(by) == {"missing_image", "missing_frame", "evil_class", "missing_key", "truncated"}
    assert "missing CAM_F0 image of frame 2" in by["missing_image"].reason and by["missing_image"].item.endswith(".jpg")
    assert "missing frame" in by["missing_frame"].reason
    assert "Evil" in by["evil_class"].reason or "getcwd" in by["evil_class"].reason
    assert by["evil_class"].item.endswith("broken_evil_class.pkl")
    assert "ego2global_rotation" in by["missing_key"].reason
    assert "corrupt pickle" in by["truncated"].reason


def test_missing_split_is_an_error(navsim_root):
    with pytest.raises(SourceError, match="does not exist"):
        NavsimReader(NavsimConfig(root=navsim_root, split="trainval")).list_items()
