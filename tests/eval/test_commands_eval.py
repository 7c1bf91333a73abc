"""`labeler_lean`: the mirror check beside `resim eval commands`' mean headings."""
from types import SimpleNamespace

import numpy as np
import pytest

from resim.eval.command_following import flow_commands, labeler_lean


class SideLabeler:
    """Heading = brightness of the last frame's left half minus its right half (a video's own "turn"), plus a
    fixed ``bias``: the labeler's lean."""

    def __init__(self, bias: float):
        self.bias = bias

    def label(self, frames, fps_hz):
        f = np.asarray(frames[-1], np.float64)
        w = f.shape[1] // 2
        yaw = f[:, :w].mean() - f[:, w:].mean() + self.bias
        return SimpleNamespace(command="Moving forward", yaw_deg=yaw)


@pytest.mark.parametrize("bias", [0.0, 3.0])
def test_the_mirror_check_reads_the_labelers_lean_not_the_videos(bias):
    rng = np.random.default_rng(0)
    videos = rng.integers(0, 255, (4, 5, 8, 12, 3), dtype=np.uint8)
    videos[:, :, :, :6] //= 2                          # every video "turns" right by the labeler's reading
    lab = SideLabeler(bias)
    _, yaws = flow_commands(videos, 2, 10.0, lab)
    assert np.mean(yaws) < bias - 20                   # the videos' own lean is large ...
    assert labeler_lean(videos, yaws, 2, 10.0, lab) == pytest.approx(bias)   # ... and not counted as the labeler's
