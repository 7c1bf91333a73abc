"""Fixtures for tests/sources: tiny datasets in the real layouts, built per session.

The NAVSIM and Bench2Drive fixtures are written here by hand from the format notes
(docs/sources.md), independently of the synthetic world's writers, so the readers are
tested against the spec and not only against our own writer.
"""
from __future__ import annotations

import gzip
import hashlib
import json
import math
import os
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def _shared_candidates():
    env = os.environ.get("RESIM_SHARED_DIR")
    if env:
        yield Path(env)
    yield REPO.parent / "shared"            # a checkout beside shared/ (the main clone)
    yield REPO.parent.parent / "shared"     # a worktree one level deeper (wt/<name>)


@pytest.fixture(scope="session")
def shared_formats() -> Path:
    for c in _shared_candidates():
        if (c / "data" / "formats" / "leaderboard").is_dir():
            return c / "data" / "formats"
    pytest.skip("shared/data/formats is absent (a user's clone has none); these tests read the real "
                "leaderboard results files from it")


@pytest.fixture(scope="session")
def shared_dashcam() -> Path:
    for c in _shared_candidates():
        if (c / "data" / "dashcam" / "solidWhiteRight.mp4").is_file():
            return c / "data" / "dashcam"
    pytest.skip("shared/data/dashcam is absent; this test reads a real dashcam clip from it")


def _img(i: int, h=48, w=80) -> np.ndarray:
    rng = np.random.default_rng(i)
    return rng.integers(0, 255, (h, w, 3), dtype=np.uint8)


# ---- OpenDV ---------------------------------------------------------------------------------
def write_video(path: Path, n: int, fps: float, h=48, w=80):
    path.parent.mkdir(parents=True, exist_ok=True)
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for i in range(n):
        f = np.zeros((h, w, 3), np.uint8)
        f[:] = (i * 7) % 255            # frame index readable from the mean brightness
        vw.write(f)
    vw.release()


@pytest.fixture(scope="session")
def opendv_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("opendv")
    write_video(root / "chanA" / "good.mp4", 30, 30.0)          # 1.0 s at 30 fps
    write_video(root / "chanA" / "with_csv.mp4", 40, 20.0)      # 2.0 s at 20 fps; csv discards 0.5 s / 0.5 s
    write_video(root / "chanB" / "small.mp4", 20, 10.0, h=16, w=32)  # under min height
    write_video(root / "chanB" / "truncated.mp4", 30, 30.0)
    p = root / "chanB" / "truncated.mp4"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])   # moov atom lost: unreadable
    (root / "chanB" / "empty.mkv").write_bytes(b"")
    (root / "videos.csv").write_text("video_id,start_discard_s,end_discard_s,notes\n"
                                     "chanA/with_csv,0.5,0.5,test row\n")
    return root


# ---- NAVSIM ---------------------------------------------------------------------------------
def navsim_frame(log: str, j: int, yaw: float, xy, token: str) -> dict:
    q = np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])
    return {
        "token": token, "frame_idx": j, "timestamp": 1633943481199607 + j * 500_000, "log_name": log,
        "log_token": "lt", "scene_name": "log-0001-scene-0001", "scene_token": "st",
        "map_location": "us-nv-las-vegas-strip", "roadblock_ids": ["1"], "vehicle_name": "v",
        "can_bus": np.zeros(18), "lidar_path": f"{log}/MergedPointCloud/{token}.pcd",
        "lidar2ego_translation": np.zeros(3), "lidar2ego_rotation": [1.0, 0.0, 0.0, 0.0],
        "ego2global_translation": np.array([xy[0], xy[1], 0.0]), "ego2global_rotation": q,
        "ego_dynamic_state": [5.0, 0.0, 0.0, 0.0], "traffic_lights": [],
        "driving_command": np.array([0, 1, 0, 0]),
        "cams": {c: {"data_path": f"{log}/{c}/{token}.jpg", "sensor2lidar_rotation": np.eye(3),
                     "sensor2lidar_translation": np.zeros(3), "cam_intrinsic": np.eye(3), "distortion": np.zeros(5)}
                 for c in ("CAM_F0", "CAM_L0", "CAM_R0", "CAM_B0")},
        "sample_prev": None, "sample_next": None,
        "anns": {"gt_boxes": np.zeros((0, 7)), "gt_names": np.array([], dtype="<U10"),
                 "gt_velocity_3d": np.zeros((0, 3)), "instance_tokens": [], "track_tokens": []},
    }


class Evil:  # a class NAVSIM never pickles: the restricted unpickler must refuse it
    def __reduce__(self):
        return (os.getcwd, ())


def make_navsim_log(root: Path, split: str, log: str, n: int, broken: str | None = None, protocol: int = 5):
    logs = root / "navsim_logs" / split
    logs.mkdir(parents=True, exist_ok=True)
    frames = []
    for j in range(n):
        tok = hashlib.sha256(f"{log}/{j}".encode()).hexdigest()[:16]
        yaw = 0.1 * j
        frames.append(navsim_frame(log, j, yaw, (2.0 * j, 0.5 * j * j), tok))
        img_dir = root / "sensor_blobs" / split / log / "CAM_F0"
        img_dir.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(img_dir / f"{tok}.jpg"), _img(j))
    if broken == "missing_image":
        (root / "sensor_blobs" / split / frames[2]["cams"]["CAM_F0"]["data_path"]).unlink()
    if broken == "missing_frame":
        del frames[3]                       # a 1 s gap in a 2 Hz log
    if broken == "evil_class":
        frames[1]["extra"] = Evil()
    if broken == "missing_key":
        del frames[1]["ego2global_rotation"]
    data = pickle.dumps(frames, protocol=protocol)
    if broken == "truncated":
        data = data[: len(data) // 2]
    (logs / f"{log}.pkl").write_bytes(data)
    return frames


@pytest.fixture(scope="session")
def navsim_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("navsim")
    make_navsim_log(root, "mini", "2021.05.12.22.00.38_veh-35_01008_01518", 6)
    make_navsim_log(root, "mini", "good_protocol4", 5, protocol=4)
    for b in ("missing_image", "missing_frame", "evil_class", "missing_key", "truncated"):
        make_navsim_log(root, "mini", f"broken_{b}", 6, broken=b)
    return root


# ---- Bench2Drive ------------------------------------------------------------------------------
def b2d_anno(x, y, theta, speed=5.0) -> dict:
    return {"x": x, "y": y, "theta": theta, "speed": speed, "throttle": 0.5, "steer": 0.0, "brake": 0.0,
            "reverse": False, "command_near": 4, "x_command_near": x, "y_command_near": y,
            "command_far": 4, "weather": {"cloudiness": 0.0},
            "bounding_boxes": [{"class": "ego_vehicle", "location": [x, y, 0.0], "rotation": [0.0, 0.0, 0.0],
                                "extent": [2.4, 1.0, 0.8]}], "sensors": {}}


def make_b2d_route(root: Path, name: str, annos: list, broken: str | None = None):
    d = root / name
    (d / "anno").mkdir(parents=True, exist_ok=True)
    (d / "camera" / "rgb_front").mkdir(parents=True, exist_ok=True)
    for i, a in enumerate(annos):
        with gzip.open(d / "anno" / f"{i:05d}.json.gz", "wt", encoding="utf-8") as f:
            json.dump(a, f, indent=4)
        cv2.imwrite(str(d / "camera" / "rgb_front" / f"{i:05d}.jpg"), _img(i), [cv2.IMWRITE_JPEG_QUALITY, 20])
    if broken == "malformed":
        (d / "anno" / "00002.json.gz").write_bytes(b"\x1f\x8b\x08garbage")
    if broken == "missing_rgb":
        (d / "camera" / "rgb_front" / "00003.jpg").unlink()
    if broken == "missing_anno":
        (d / "anno" / "00001.json.gz").unlink()
    if broken == "bad_jpeg":
        (d / "camera" / "rgb_front" / "00004.jpg").write_bytes(b"not a jpeg")


def straight_east(n=6, theta=math.pi / 2):
    return [b2d_anno(10.0 + 0.5 * i, 20.0, theta) for i in range(n)]


@pytest.fixture(scope="session")
def carla_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("carla")
    make_b2d_route(root, "HardBreakRoute_Town01_Route30_Weather3", straight_east())
    # driving north in CARLA = towards -y (left-handed); compass theta = 0
    make_b2d_route(root, "Accident_Town03_Route24816_Weather25", [b2d_anno(0.0, -0.5 * i, 0.0) for i in range(6)])
    nan_one = straight_east(10)
    nan_one[4]["theta"] = float("nan")
    make_b2d_route(root, "NanTheta_Town01_Route31_Weather3", nan_one)
    make_b2d_route(root, "AllNan_Town01_Route32_Weather3", straight_east(5, float("nan")))
    for b, num in (("malformed", 33), ("missing_rgb", 34), ("missing_anno", 35), ("bad_jpeg", 36)):
        make_b2d_route(root, f"Broken{b.title().replace('_', '')}_Town01_Route{num}_Weather3", straight_east(), b)
    results = {"_checkpoint": {"global_record": {}, "progress": [2, 2], "records": [
        {"index": 0, "route_id": "RouteScenario_30_rep0", "status": "Completed", "num_infractions": 1,
         "infractions": {"collisions_vehicle": ["Agent collided against object with type=vehicle.a and id=1 at "
                                                "(x=1.0, y=2.0, z=0.0)"], "red_light": []},
         "scores": {"score_route": 100, "score_penalty": 0.6, "score_composed": 60.0}, "meta": {}},
        {"index": 1, "route_id": "RouteScenario_24816_rep0", "status": "Perfect", "num_infractions": 0,
         "infractions": {"collisions_vehicle": []},
         "scores": {"score_route": 100.0, "score_penalty": 1.0, "score_composed": 100.0}, "meta": {}},
    ]}, "entry_status": "Finished", "eligible": True, "sensors": [], "values": [], "labels": []}
    (root / "results.json").write_text(json.dumps(results))
    (root / "broken_results.json").write_text("{\"_checkpoint\": ")
    return root


# ---- synthetic --------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def synth_dir(tmp_path_factory) -> Path:
    from resim.pipeline.sources.synth.generate import generate, preset

    out = tmp_path_factory.mktemp("synth") / "world"
    generate(out, 6, seed=7, cfg=preset("tiny"), progress=False)
    return out
