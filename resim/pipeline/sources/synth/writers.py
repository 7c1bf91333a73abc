"""Write synthetic episodes into the three real layouts.

* OpenDV:  ``opendv/synth/<episode>.mp4`` (OpenCV ``mp4v``, deterministic bytes) and
  ``opendv/videos.csv`` (video_id, start_discard_s = 0, end_discard_s = 0, notes).
* NAVSIM:  ``navsim/navsim_logs/<split>/<log>.pkl`` (a list of per-frame dicts with the
  keys of a real OpenScene/NAVSIM log, numpy arrays, ``pickle.HIGHEST_PROTOCOL``) and
  ``navsim/sensor_blobs/<split>/<log>/CAM_F0/<16-hex token>.jpg``. Logs are 2 Hz like
  NAVSIM's: key frame j is simulation step ``j * sim_hz / 2``; no other frames are written
  (real NAVSIM logs also hold only the 2 Hz key frames). Only CAM_F0 is rendered, so
  ``cams`` has that one key; ``lidar_path`` names a file that is not written;
  ``map_location`` is ``"synthetic"``.
* CARLA:   ``carla/<Scenario>_Town90_Route<id>_Weather<w>/anno/NNNNN.json.gz`` (10 Hz,
  CARLA left-handed coordinates and compass theta) and ``camera/rgb_front/NNNNN.jpg``,
  plus ``carla/simulation_results.json`` in the Bench2Drive/LB2 results format.

Everything is deterministic: no timestamps from the clock, gzip with mtime 0.
"""
from __future__ import annotations

import csv
import gzip
import hashlib
import io
import json
import math
import pickle
from pathlib import Path

import cv2
import numpy as np

from ..carla import ours_to_carla
from ..navsim import yaw_quaternion
from resim.synthworld.drivers import Trace
from resim.synthworld.score import Score

NAVSIM_T0_US = 1_700_000_000_000_000     # synthetic logs start at this Unix time (us)
ROAD_OPTION = {"left": 1, "right": 2, "straight": 3, "lanefollow": 4}


def _jpeg(img_rgb: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")  # our bug / OpenCV broken
    return buf.tobytes()


def write_opendv_video(path: Path, frames: list[np.ndarray], fps_hz: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps_hz), (w, h))
    if not vw.isOpened():
        raise RuntimeError(f"OpenCV cannot write mp4v to {path}")
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()


def write_opendv_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        wr = csv.DictWriter(f, fieldnames=["video_id", "start_discard_s", "end_discard_s", "notes"], lineterminator="\n")
        wr.writeheader()
        wr.writerows(rows)


def _token(*parts) -> str:
    return hashlib.sha256("/".join(str(p) for p in parts).encode()).hexdigest()[:16]


def navsim_command(turn: str) -> np.ndarray:
    """NAVSIM one-hot (left, straight, right, unknown)."""
    return np.eye(4, dtype=np.int64)[{"left": 0, "straight": 1, "right": 2}.get(turn, 3)]


def write_navsim_log(root: Path, split: str, log_name: str, tr: Trace, steps: list[int], frames: list[np.ndarray],
                     turns: list[str], K: np.ndarray, jpeg_quality: int) -> None:
    logs = root / "navsim_logs" / split
    blobs = root / "sensor_blobs" / split / log_name / "CAM_F0"
    logs.mkdir(parents=True, exist_ok=True)
    blobs.mkdir(parents=True, exist_ok=True)
    tokens = [_token(log_name, s) for s in steps]
    out = []
    for j, (s, img) in enumerate(zip(steps, frames)):
        x, y, yaw = (float(v) for v in tr.poses[s])
        q = yaw_quaternion(yaw)
        t = np.array([x, y, 0.0])
        v = float(tr.speed_mps[s])
        acc = float(tr.accel_mps2[s])
        yaw_rate = float(tr.curvature[s] * v)
        can_bus = np.r_[t, q, [acc, v * yaw_rate, 0.0], [v, 0.0, 0.0], [0.0, 0.0, yaw_rate], [0.0, 0.0]]
        ego2global = np.eye(4)
        ego2global[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        ego2global[:3, 3] = t
        rel = f"{log_name}/CAM_F0/{tokens[j]}.jpg"
        (blobs / f"{tokens[j]}.jpg").write_bytes(_jpeg(img, jpeg_quality))
        # camera: x forward 1.0 m, z 1.5 m, looking along ego x (optical frame: z fwd, x right, y down)
        cam_rot = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
        out.append({
            "token": tokens[j], "frame_idx": j, "timestamp": NAVSIM_T0_US + int(round(tr.t_s[s] * 1e6)),
            "log_name": log_name, "log_token": _token("log", log_name), "scene_name": f"{log_name}-scene-0000",
            "scene_token": _token("scene", log_name), "map_location": "synthetic",
            "roadblock_ids": ["synthetic-route"], "vehicle_name": "synthetic-ego",
            "can_bus": can_bus, "lidar_path": f"{log_name}/MergedPointCloud/{tokens[j]}.pcd",
            "lidar2ego_translation": np.zeros(3), "lidar2ego_rotation": [1.0, 0.0, 0.0, 0.0],
            "ego2global_translation": t, "ego2global_rotation": q,
            "ego_dynamic_state": [v, 0.0, acc, v * yaw_rate],
            "traffic_lights": [], "driving_command": navsim_command(turns[j]),
            "cams": {"CAM_F0": {"data_path": rel, "sensor2lidar_rotation": cam_rot,
                                "sensor2lidar_translation": np.array([1.0, 0.0, 1.5]),
                                "cam_intrinsic": K.copy(), "distortion": np.zeros(5)}},
            "sample_prev": tokens[j - 1] if j else None, "sample_next": tokens[j + 1] if j + 1 < len(steps) else None,
            "ego2global": ego2global, "lidar2ego": np.eye(4), "lidar2global": ego2global.copy(),
            "anns": {"gt_boxes": np.zeros((0, 7)), "gt_names": np.array([], dtype="<U10"),
                     "gt_velocity_3d": np.zeros((0, 3)), "instance_tokens": [], "track_tokens": []},
        })
    (logs / f"{log_name}.pkl").write_bytes(pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL))


def _gz_json(obj) -> bytes:
    raw = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz:
        gz.write(json.dumps(obj, indent=4).encode("utf-8"))
    return raw.getvalue()


WEATHERS = {  # appearance name -> (weather id, carla.WeatherParameters subset)
    "clear": (1, {"cloudiness": 5.0, "precipitation": 0.0, "fog_density": 2.0, "sun_altitude_angle": 45.0}),
    "overcast": (3, {"cloudiness": 80.0, "precipitation": 0.0, "fog_density": 10.0, "sun_altitude_angle": 35.0}),
    "dusk": (8, {"cloudiness": 30.0, "precipitation": 0.0, "fog_density": 10.0, "sun_altitude_angle": 5.0}),
    "fog": (20, {"cloudiness": 90.0, "precipitation": 0.0, "fog_density": 60.0, "sun_altitude_angle": 20.0}),
    "night": (21, {"cloudiness": 10.0, "precipitation": 0.0, "fog_density": 5.0, "sun_altitude_angle": -80.0}),
}


def write_carla_route(folder: Path, tr: Trace, steps: list[int], frames: list[np.ndarray], options: list[str],
                      targets: list[tuple[float, float]], weather: str, K: np.ndarray, jpeg_quality: int) -> None:
    (folder / "anno").mkdir(parents=True, exist_ok=True)
    (folder / "camera" / "rgb_front").mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    fov = math.degrees(2 * math.atan(w / 2 / K[0, 0]))
    for i, (s, img) in enumerate(zip(steps, frames)):
        x, y, yaw = (float(v) for v in tr.poses[s])
        cx, cy, theta = ours_to_carla(x, y, yaw)
        v = float(tr.speed_mps[s])
        tx, ty, _ = ours_to_carla(targets[i][0], targets[i][1], 0.0)
        yaw_carla_deg = math.degrees(-yaw)        # left-handed yaw = -(right-handed yaw)
        k = float(tr.curvature[s])
        anno = {
            "x": cx, "y": cy, "theta": theta, "speed": v,
            "throttle": float(tr.throttle[s]), "steer": float(np.clip(-k / 0.2, -1, 1)), "brake": float(tr.brake[s]),
            "reverse": False,
            "x_command_far": tx, "y_command_far": ty, "command_far": ROAD_OPTION[options[i]],
            "x_command_near": tx, "y_command_near": ty, "command_near": ROAD_OPTION[options[i]],
            "x_target": tx, "y_target": ty, "next_command": ROAD_OPTION[options[i]],
            "should_brake": int(tr.brake[s] > 0.3), "only_ap_brake": 0,
            "weather": WEATHERS[weather][1],
            "acceleration": [float(tr.accel_mps2[s]), float(-k * v * v), 0.0],
            "angular_velocity": [0.0, 0.0, float(-k * v)],
            "bounding_boxes": [{
                "class": "ego_vehicle", "id": "0", "type_id": "vehicle.synthetic.ego", "base_type": "car",
                "location": [cx, cy, 0.0], "center": [cx, cy, 0.75], "rotation": [0.0, 0.0, yaw_carla_deg],
                "extent": [2.25, 0.95, 0.75], "speed": v, "distance": 0.0,
            }],
            "sensors": {"CAM_FRONT": {
                "location": [cx + math.cos(-yaw), cy + math.sin(-yaw), 1.5], "rotation": [0.0, 0.0, yaw_carla_deg],
                "intrinsic": K.tolist(), "fov": fov, "image_size_x": w, "image_size_y": h,
                "cam2ego": [[1, 0, 0, 1.0], [0, 1, 0, 0], [0, 0, 1, 1.5], [0, 0, 0, 1]],
            }},
        }
        (folder / "anno" / f"{i:05d}.json.gz").write_bytes(_gz_json(anno))
        (folder / "camera" / "rgb_front" / f"{i:05d}.jpg").write_bytes(_jpeg(img, jpeg_quality))


def route_record(route_num: int, folder_name: str, scenario: str, weather_id: int, score: Score,
                 route_length_m: float, duration_s: float) -> dict:
    inf = score.infractions
    return {
        "index": route_num, "route_id": f"RouteScenario_{route_num}_rep0", "scenario_name": scenario,
        "weather_id": str(weather_id), "save_name": folder_name, "town_name": "Town90",
        "status": score.status, "num_infractions": sum(len(v) for v in inf.values()), "infractions": inf,
        "scores": {"score_route": score.score_route, "score_penalty": score.score_penalty,
                   "score_composed": score.score_composed},
        "meta": {"route_length": round(route_length_m, 3), "duration_game": round(duration_s, 3),
                 "duration_system": 0.0},
    }


def results_json(records: list[dict]) -> dict:
    n = len(records)
    mean = lambda k: round(float(np.mean([r["scores"][k] for r in records])), 6) if n else 0.0  # noqa: E731
    return {
        "_checkpoint": {
            "global_record": {
                "index": -1, "route_id": -1,
                "status": "Perfect" if all(r["status"] == "Perfect" for r in records) else "Failed",
                "scores_mean": {k: mean(k) for k in ("score_composed", "score_route", "score_penalty")},
                "meta": {"total_length": round(sum(r["meta"]["route_length"] for r in records), 3),
                         "exceptions": [[r["route_id"], r["index"], r["status"]] for r in records
                                        if r["status"] not in ("Perfect", "Completed")]},
            },
            "progress": [n, n],
            "records": records,
        },
        "entry_status": "Finished", "eligible": True, "sensors": ["carla_camera", "carla_imu", "carla_speedometer"],
        "values": [], "labels": [],
    }
