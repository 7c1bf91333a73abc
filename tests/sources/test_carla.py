import math

import numpy as np
import pytest

from resim.pipeline.sources.carla import CarlaConfig, CarlaReader, carla_to_ours, ours_to_carla
from resim.pipeline.sources.episode import scan_items


def test_coordinate_conversion_is_right_handed():
    # driving east (+x) in CARLA: compass theta = pi/2 -> our yaw 0
    assert np.allclose(carla_to_ours([1.0], [2.0], [math.pi / 2]), [[1.0, -2.0, 0.0]])
    # driving north in CARLA (towards -y): theta = 0 -> our yaw +pi/2, i.e. towards +y
    assert np.allclose(carla_to_ours([0.0], [-3.0], [0.0]), [[0.0, 3.0, math.pi / 2]])
    for yaw in (-2.0, 0.3, 3.0):
        x, y, th = ours_to_carla(1.5, -2.5, yaw)
        back = carla_to_ours([x], [y], [th])[0]
        assert np.allclose(back[:2], [1.5, -2.5]) and math.isclose(math.remainder(back[2] - yaw, 2 * math.pi), 0,
                                                                   abs_tol=1e-12)


def test_reads_route_folder_and_outcome(carla_root):
    r = CarlaReader(CarlaConfig(root=carla_root))
    ep = r.open("HardBreakRoute_Town01_Route30_Weather3")
    assert ep.source == "carla" and ep.fps_hz == 10.0 and ep.num_frames == 6 and ep.frame_size_hw == (48, 80)
    assert np.allclose(ep.poses[:, 2], 0.0) and np.allclose(ep.poses[:, 1], -20.0)
    assert np.allclose(np.diff(ep.poses[:, 0]), 0.5)
    assert ep.outcome.infraction_score == 0.6 and ep.outcome.hazard and ep.outcome.infractions == ["collisions_vehicle"]
    assert (ep.driving_command[:, 1] == 1).all()          # LANEFOLLOW -> straight
    north = r.open("Accident_Town03_Route24816_Weather25")
    assert np.allclose(north.poses[:, 2], math.pi / 2) and (np.diff(north.poses[:, 1]) > 0).all()
    assert north.outcome.infraction_score == 1.0 and not north.outcome.hazard
    # heading agrees with the direction of motion in both
    for e in (ep, north):
        d = np.diff(e.poses[:, :2], axis=0)
        assert np.allclose(np.arctan2(d[:, 1], d[:, 0]), e.poses[:-1, 2])
    assert [p.item.endswith("broken_results.json") for p in r.problems] == [True]
    frames = list(ep.frames(1, 3, size_hw=(24, 40)))
    assert len(frames) == 2 and frames[0].shape == (24, 40, 3)


def test_nan_theta_interpolated_and_reported(carla_root):
    ep = CarlaReader(CarlaConfig(root=carla_root)).open("NanTheta_Town01_Route31_Weather3")
    assert np.isfinite(ep.poses).all() and np.allclose(ep.poses[:, 2], 0.0)
    assert any("NaN" in w and "interpolated" in w for w in ep.warnings)


def test_broken_routes_reported_with_item_and_reason(carla_root):
    good, problems = scan_items(CarlaReader(CarlaConfig(root=carla_root)))
    assert sorted(good) == ["Accident_Town03_Route24816_Weather25", "HardBreakRoute_Town01_Route30_Weather3",
                            "NanTheta_Town01_Route31_Weather3"]
    reasons = {p.item: p.reason for p in problems}
    assert len(reasons) == 5
    txt = "\n".join(f"{k}: {v}" for k, v in reasons.items())
    assert "AllNan_Town01_Route32_Weather3: compass theta is NaN in 5/5" in txt
    assert "00002.json.gz: malformed annotation" in txt
    assert "rgb_front/00003.jpg: missing rgb_front frame 3" in txt
    assert "anno/00001.json.gz: missing annotation frame 1" in txt
    assert "rgb_front/00004.jpg: cannot decode image" in txt


def test_results_read_error_propagates_and_is_not_cached(carla_root, monkeypatch):
    import errno

    from resim.pipeline.sources import carla

    real, calls = carla.load_results, {"n": 0}

    def eio_once(p):
        calls["n"] += 1
        if calls["n"] == 1:
            raise OSError(errno.EIO, "Input/output error", str(p))
        return real(p)
    monkeypatch.setattr(carla, "load_results", eio_once)
    r = CarlaReader(CarlaConfig(root=carla_root))
    with pytest.raises(OSError):                                   # transient: the pipeline retries it
        r.open("HardBreakRoute_Town01_Route30_Weather3")
    ep = r.open("HardBreakRoute_Town01_Route30_Weather3")           # the retry reads every file again
    assert ep.outcome is not None and ep.outcome.infraction_score == 0.6 and ep.warnings == []
    assert [p.item.endswith("broken_results.json") for p in r.problems] == [True]   # once, not twice
