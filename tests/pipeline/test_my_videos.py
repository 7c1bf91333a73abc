"""The laptop config for a folder of one's own videos (configs/pipeline/my_videos.yaml), and `resim pipeline check`'s
warnings about videos a config would make nothing from (resim/pipeline/video_preflight.py)."""
import numpy as np
import pytest

from resim.cli import main
from resim.pipeline.load import load_config
from resim.pipeline.runner import pool_names

from .conftest import REPO

MY_VIDEOS = str(REPO / "configs/pipeline/my_videos.yaml")
OPENDV = str(REPO / "configs/pipeline/opendv.yaml")


def _video(path, seconds: float, height: int = 360, width: int = 640, fps: int = 10):
    """A small H.264 dashcam stand-in written with PyAV (what the OpenDV reader and the probe both open)."""
    av = pytest.importorskip("av")
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = width, height, "yuv420p"
        for i in range(int(seconds * fps)):
            f = av.VideoFrame.from_ndarray(np.full((height, width, 3), 4 * i % 256, np.uint8), format="rgb24")
            for pkt in s.encode(f):
                c.mux(pkt)
        for pkt in s.encode():
            c.mux(pkt)
    return path


def _check(capsys, config, root, tmp_path, *extra):
    rc = main(["pipeline", "check", config, "--out", str(tmp_path / "out"), "--set", f"sources.opendv.root={root}",
               *extra])
    cap = capsys.readouterr()
    return rc, cap.out, [line for line in cap.err.splitlines() if line.strip()]


def test_laptop_config_reads_a_folder_of_videos_and_check_accepts_it(tmp_path, capsys):
    videos = tmp_path / "dashcam"
    _video(videos / "2026-05-01" / "drive.mp4", 6.0)      # sub-folders are part of the layout (read recursively)
    cfg = load_config(MY_VIDEOS, [f"sources.opendv.root={videos}"], out=tmp_path / "out")
    o = cfg.sources.opendv
    assert cfg.ray.address is None and cfg.ray.executor == "ray"                       # embedded, no cluster
    assert o.start_discard_s + o.end_discard_s <= 10 and o.min_height_px <= 480
    # one actor of every pool fits 2 cores at once (resim/pipeline/stage_fit.py: else a pool may never start)
    pools = [n for n in pool_names(cfg) if n != "prompts"]
    assert sum(getattr(cfg.ray.stages, n).num_cpus for n in pools) <= 2
    assert all(getattr(cfg.ray.stages, n).num_cpus <= 2 for n in pool_names(cfg))
    rc, out, warnings = _check(capsys, MY_VIDEOS, videos, tmp_path)
    assert rc == 0 and "address: null" in out and f"root: {videos}" in out
    assert warnings == []


def test_check_warns_where_discards_or_min_height_leave_nothing(tmp_path, capsys):
    videos = tmp_path / "dashcam"
    _video(videos / "a.mp4", 6.0)                      # 360p, 6 s
    _video(videos / "b.mp4", 3.0)                      # shorter than one 4.9 s clip
    rc, _, warnings = _check(capsys, OPENDV, videos, tmp_path)     # the cluster config: 90 s + 60 s, >= 720 px
    assert rc == 0, warnings                           # warnings only: the config itself is valid
    assert len(warnings) == 3, warnings
    assert warnings[0] == ("warning: sources.opendv: a.mp4 lasts 6.0 s and the discards (start 90 s + end 60 s) "
                           "exceed it: it gives no clip (lower sources.opendv.start_discard_s / end_discard_s, or set "
                           "them per video in videos.csv)")
    assert warnings[2] == ("warning: sources.opendv: all 2 videos are lower than min_height_px 720 (heights 360 px): "
                           "every one would be quarantined; lower it, e.g. --set sources.opendv.min_height_px=360")
    rc, _, warnings = _check(capsys, MY_VIDEOS, videos, tmp_path)
    assert rc == 0 and warnings == [
        "warning: sources.opendv: b.mp4 lasts 3.0 s and the discards (start 0 s + end 0 s) leave 3.0 s, less than "
        "one 4.9 s clip: it gives no clip (lower sources.opendv.start_discard_s / end_discard_s, or set them per "
        "video in videos.csv)"]


def test_real_dashcam_clips_pass_the_laptop_check(shared_dir, tmp_path, capsys):
    dashcam = shared_dir / "data" / "dashcam"
    if not any(dashcam.glob("*.mp4")):
        pytest.skip(f"{dashcam} holds no dashcam clips")
    rc, _, warnings = _check(capsys, MY_VIDEOS, dashcam, tmp_path)
    assert rc == 0 and warnings == []                  # 540p and 576p clips of 8.8 s and 10 s
    rc, _, warnings = _check(capsys, OPENDV, dashcam, tmp_path)
    assert rc == 0 and any("lower than min_height_px 720" in w for w in warnings), warnings
