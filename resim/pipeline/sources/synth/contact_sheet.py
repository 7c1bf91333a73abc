"""Contact sheet of synthetic episodes, read back through the real readers."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..carla import CarlaConfig, CarlaReader
from ..navsim import NavsimConfig, NavsimReader
from ..opendv import OpenDVConfig, OpenDVReader
from .ground_truth import GroundTruth


def contact_sheet(root: str | Path, out_png: str | Path, max_episodes: int = 6, columns: int = 6,
                  size_hw: tuple[int, int] = (128, 224)) -> Path:
    """One row per episode (frames evenly spread over it), labelled with reader, driver and score."""
    root = Path(root)
    gt = GroundTruth.load(root)
    split = gt.data["config"]["navsim_split"]
    readers = {
        "opendv": OpenDVReader(OpenDVConfig.preset("synthetic", root=str(root / "opendv"))),
        "navsim": NavsimReader(NavsimConfig(root=root / "navsim", split=split)),
        "carla": CarlaReader(CarlaConfig(root=root / "carla")),
    }
    # prefer a mix: hazardous episodes first so they are on the sheet, then the others
    eps = sorted(gt.episodes, key=lambda e: (e["driver"] != "explorer", e["index"]))[:max_episodes]
    eps.sort(key=lambda e: e["index"])
    rows = []
    for e in eps:
        lay = e["layout"]
        ep = readers[lay["reader"]].open(lay["item_id"])
        idx = np.linspace(0, ep.num_frames - 1, columns).round().astype(int)
        frames = {}
        for k, f in enumerate(ep.frames(0, ep.num_frames, size_hw=size_hw)):
            if k in idx:
                frames[k] = f
        yaw = gt.yaw_for(lay["reader"], lay["item_id"])
        tiles = []
        for k in idx:
            tile = np.ascontiguousarray(frames[int(k)])
            cv2.putText(tile, f"t={k / ep.fps_hz:.1f}s yaw={np.degrees(yaw[k] - yaw[0]):+.0f}", (3, size_hw[0] - 5),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
        row = np.concatenate(tiles, axis=1)
        o = e["outcome"]
        label = (f"{lay['reader']}: {e['episode']}  {e['driver']}{'/' + e['pattern'] if e['pattern'] else ''}  "
                 f"{e['appearance']}  infraction score {o['infraction_score']:.2f} {','.join(sorted(set(o['infractions'])))}")
        bar = np.full((16, row.shape[1], 3), 30, np.uint8)
        cv2.putText(bar, label, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(np.concatenate([bar, row], axis=0))
    sheet = np.concatenate(rows, axis=0)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_png), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out_png
