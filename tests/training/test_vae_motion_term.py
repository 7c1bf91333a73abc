"""The motion term of `resim train vae` (resim/train/tasks/vae_motion.py): the original's optical flow, the warp along it,
and an L1 that is zero for a perfect reconstruction, small for errors that move with the scene and large for
texture that stays put while the scene pans."""
import cv2
import numpy as np
import pytest
import torch

from resim.config import ConfigError
from resim.train.tasks.vae import build_vae
from resim.train.tasks.vae_motion import backward_flow, motion_l1, warp

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _pan(px_per_frame: float, t: int = 9, seed: int = 0, h: int = 32, w: int = 48) -> torch.Tensor:
    """uint8 (1, T, 3, H, W): a smooth random texture panning right by ``px_per_frame`` (sub-pixel: resampled)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, 4 * w)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 20, 230, cv2.NORM_MINMAX)
    frames = []
    for k in range(t):
        m = np.float32([[1, 0, w + px_per_frame * k], [0, 1, 0]])     # output(x) = tex(x - shift)
        frames.append(cv2.warpAffine(tex, m, (4 * w, h), flags=cv2.INTER_CUBIC)[:, 2 * w:3 * w])
    v = np.clip(np.stack(frames), 0, 255).round().astype(np.uint8)
    return torch.from_numpy(np.repeat(v[:, None], 3, axis=1))[None]


def _signal(frames: torch.Tensor) -> torch.Tensor:
    return frames.permute(0, 2, 1, 3, 4).float() / 127.5 - 1.0          # (B, 3, T, H, W) in [-1, 1]


def test_flow_reads_a_sub_pixel_pan_and_the_warp_follows_it():
    frames = _pan(0.7)
    fl = backward_flow(frames)
    assert fl.shape == (1, 8, 2, 32, 48)
    inner = fl[0, :, :, 6:-6, 6:-6]
    # frame t+1 at x looks like frame t at x - 0.7: the backward flow is -0.7 px in x, 0 in y
    assert inner[:, 0].mean().item() == pytest.approx(-0.7, abs=0.1) and inner[:, 1].abs().mean() < 0.1
    x = _signal(frames)
    moved, valid = warp(x, fl)
    err_warped = ((moved - x[:, :, 1:]).abs() * valid).sum() / (valid.sum() * 3)
    err_still = (x[:, :, :-1] - x[:, :, 1:]).abs().mean()
    assert err_warped < 0.35 * err_still, (float(err_warped), float(err_still))
    with pytest.raises(ValueError, match="uint8"):
        backward_flow(frames.float())


def test_motion_l1_tells_texture_that_stays_from_texture_that_moves():
    frames = _pan(1.0)
    x, fl = _signal(frames), backward_flow(frames)
    assert motion_l1(x, x, fl).item() == 0.0                                   # perfect: zero
    blurred = _signal(torch.from_numpy(np.stack([cv2.GaussianBlur(f, (0, 0), 1.0) for f in
                                                 frames[0].permute(0, 2, 3, 1).numpy()])).permute(0, 3, 1, 2)[None])
    stuck = x[:, :, :1].expand_as(x) * 0.5 + blurred * 0.5                     # half the texture does not move
    moving, staying = motion_l1(blurred, x, fl).item(), motion_l1(stuck, x, fl).item()
    assert staying > 3 * moving, (moving, staying)
    # a pixel loss alone cannot see the difference: the two errors are of a size per frame
    assert (stuck - x).abs().mean() < 4 * (blurred - x).abs().mean()


def test_motion_term_enters_the_loss():
    base = {"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9}
    batch = {"frames": _pan(1.0)}
    torch.manual_seed(0)
    plain, _ = build_vae(base).loss(batch)
    torch.manual_seed(0)
    more, logs = build_vae({**base, "motion_weight": 2.0}).loss(batch)
    assert "motion_l1" in logs and float(logs["motion_l1"]) > 0
    assert float(more.detach() - plain.detach()) == pytest.approx(2 * float(logs["motion_l1"]), abs=1e-5)
    with pytest.raises(ConfigError, match="motion_weight"):
        build_vae({**base, "motion_weight": -1.0})
