"""An OUT inside an input root is not read back as input (``resim/pipeline/sources/listing.py``).

The attack: ``--out`` inside the OpenDV root; a rerun after a kill listed the first attempt's
``OUT/_staging/<unit>/*.frames.mp4`` (a real, decodable preview) as a video and cut a clip from it. Here the
same layout is enumerated, with OUT spelled directly, through a symbolic link, and as the root itself.
"""
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from resim.pipeline.runner import EnumerateStage
from resim.pipeline.sources.listing import walk_files
from resim.pipeline.units import out_trees, spec_from_state

from .conftest import make_config


def _video(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (112, 64))
    for i in range(120):                                                # 12 s at 10 fps
        w.write(np.full((64, 112, 3), 2 * i, np.uint8))
    w.release()
    return path


@pytest.mark.parametrize("where", ["inside", "through_a_link", "is_the_root"])
def test_an_out_inside_the_opendv_root_is_not_enumerated(tmp_path, where):
    root = tmp_path / "opendv"
    real = _video(root / "channel" / "drive.mp4")
    out = root if where == "is_the_root" else root / "out"
    # what an interrupted first run left in OUT: its preview of the real video, a decodable mp4
    staged = out / "_staging" / "opendv-drive-0123456789ab" / "drive.frames.mp4"
    staged.parent.mkdir(parents=True)
    shutil.copyfile(real, staged)
    assert len(walk_files(root, (), {".mp4"})) == 2                     # without the exclusion: both are listed
    given = out
    if where == "through_a_link":
        given = tmp_path / "out-link"
        given.symlink_to(out, target_is_directory=True)

    cfg = make_config(given, ["sources.synthetic.root=null", f"sources.opendv.root={root}",
                              "sources.opendv.start_discard_s=0", "sources.opendv.end_discard_s=0",
                              "sources.opendv.min_height_px=32"])
    states, bad = EnumerateStage(cfg)()
    assert [s["item_id"] for s in states] == ["channel/drive.mp4"] and bad == []
    # the stages' readers (rebuilt from the unit's state on a worker) exclude OUT as well
    assert spec_from_state(states[0]).exclude == out_trees(cfg.out)
