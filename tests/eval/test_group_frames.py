"""The group-end reading (resim/eval/group_frames.py): frames inside each latent group redrawn by optical-flow
interpolation between the group ends. It keeps the group ends, restores a pan's in-between frames, and turns a
cross-fade between group ends (what the synthetic world's decoder draws) back into motion."""
import cv2
import numpy as np
import pytest

from resim.eval.group_frames import redraw_all, redraw_inside_groups

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _pan(px_per_frame: float, t: int = 13, seed: int = 0) -> np.ndarray:
    """(T, 64, 96, 3) uint8: a smooth random texture panning sideways, ``px_per_frame`` px per frame."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (64, 400)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 20, 230, cv2.NORM_MINMAX)
    out = []
    for k in range(t):
        m = np.float32([[1, 0, -150 - px_per_frame * k], [0, 1, 0]])     # output(x) = tex(x + 150 + shift)
        out.append(cv2.warpAffine(tex, m, (96, 64), flags=cv2.INTER_CUBIC))
    v = np.clip(np.stack(out), 0, 255).round().astype(np.uint8)
    return np.repeat(v[..., None], 3, axis=3)


def _cross_fade(v: np.ndarray, group: int = 4) -> np.ndarray:
    out = v.astype(np.float32).copy()
    for a in range(0, len(v) - group, group):
        for j in range(1, group):
            out[a + j] = (1 - j / group) * v[a] + j / group * v[a + group]
    return out.round().astype(np.uint8)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    inner = (slice(None), slice(8, -8), slice(12, -12))        # away from the edges the pan brings in
    return float(10 * np.log10(255 ** 2 / np.mean((a[inner].astype(np.float64) - b[inner]) ** 2)))


def test_group_ends_are_kept_and_a_pans_in_between_frames_restored():
    pan = _pan(1.5)
    out = redraw_inside_groups(pan)
    assert out.shape == pan.shape and out.dtype == np.uint8
    assert np.array_equal(out[::4], pan[::4])                     # frames 0, 4, 8, 12: the group ends, untouched
    inside = np.ones(len(pan), bool)
    inside[::4] = False
    assert _psnr(out[inside], pan[inside]) > 32


def test_a_cross_fade_between_group_ends_is_redrawn_as_motion():
    pan = _pan(1.5, seed=1)
    fade = _cross_fade(pan)
    inside = np.ones(len(pan), bool)
    inside[::4] = False
    before, after = _psnr(fade[inside], pan[inside]), _psnr(redraw_inside_groups(fade)[inside], pan[inside])
    assert before < 24 and after > before + 8, (before, after)


def test_frames_after_the_last_group_end_and_short_videos_are_left_alone():
    pan = _pan(1.0, t=11)                                         # group ends 0, 4, 8; frames 9, 10 after the last
    out = redraw_inside_groups(pan)
    assert np.array_equal(out[8:], pan[8:])
    assert np.array_equal(redraw_inside_groups(pan[:3]), pan[:3])
    assert redraw_all(np.stack([pan, pan])).shape == (2, *pan.shape)


def test_bad_input_is_refused_with_the_reason():
    with pytest.raises(ValueError, match="uint8 \\(T, H, W, 3\\)"):
        redraw_inside_groups(_pan(1.0).astype(np.float32))
    with pytest.raises(ValueError, match="group must be"):
        redraw_inside_groups(_pan(1.0), group=1)
