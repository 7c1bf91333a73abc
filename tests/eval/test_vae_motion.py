"""Motion through the VAE (`resim eval vae`): the flow labeler's reading of reconstructions separates a VAE
that blurs (heading kept) from one that smears the ego motion (heading lost), which PSNR alone cannot."""
import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from resim.cli import main
from resim.eval.vae_eval import format_vae_difference, format_vae_eval, motion_through, paired_vae_difference
from resim.eval.worldeval import flow_labeler_status

REPO = Path(__file__).resolve().parents[2]


def _pan(px_per_frame: float, seed: int) -> np.ndarray:
    """(49, 64, 96, 3) uint8: a texture panning sideways, as a camera yawing (left turn: content moves right)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (64, 400), dtype=np.uint8), (0, 0), 1.2)
    tex = cv2.normalize(tex, None, 20, 230, cv2.NORM_MINMAX)
    cols = [150 + int(round(px_per_frame * i)) for i in range(49)]
    return np.stack([np.repeat(tex[:, c:c + 96, None], 3, axis=2) for c in cols])


@pytest.fixture(scope="module")
def drives():
    frames = [_pan(-1.5, 0), _pan(1.5, 1), _pan(0.0, 2), _pan(-1.5, 3), _pan(1.5, 4)]
    clips = [SimpleNamespace(command=c, num_history_frames=9, fps_hz=10.0)
             for c in ("Turning left", "Turning right", "Moving forward", "Turning left", "Turning right")]
    labeler, reason = flow_labeler_status()
    assert labeler is not None, reason
    return frames, clips, labeler


def test_a_blur_keeps_the_heading_a_frozen_reconstruction_loses_it(drives):
    frames, clips, labeler = drives
    blurred = [np.stack([cv2.GaussianBlur(f, (0, 0), 1.0) for f in v]) for v in frames]
    # motion smeared: every 4-frame group shows its first frame, and the image barely moves
    frozen = [np.stack([v[min(i, 12)] for i in range(len(v))]) for v in frames]

    same = motion_through(labeler, frames, frames, clips)
    assert same["labeler_on_originals"]["accuracy"] == 1.0 and same["same_label"] == 1.0
    assert same["heading_kept"] == pytest.approx(1.0)

    blur = motion_through(labeler, frames, blurred, clips)
    assert blur["labeler_on_reconstructions"]["accuracy"] == 1.0 and blur["heading_kept"] > 0.8, blur

    lost = motion_through(labeler, frames, frozen, clips)
    assert lost["heading_kept"] < 0.2, lost
    assert lost["labeler_on_reconstructions"]["accuracy"] == pytest.approx(1 / 5), lost   # only "forward" right
    assert "on reconstructions 0.20" in format_vae_eval({"psnr_db": {"mean": 30.0, "per_clip_min": 29.0},
                                                         "ssim": {"mean": 0.9}, "clips": 5, "motion": lost})


def _by_group(v: np.ndarray, frame_of) -> np.ndarray:
    return np.stack([v[min(frame_of(t), len(v) - 1)] for t in range(len(v))])


def test_heading_kept_by_place_in_the_latent_group(drives):
    """Where inside a 4-frame latent group the heading goes: kept whole at every place when the frames are the
    originals; a decoder that holds each group on its end frame moves only across the group boundary (place 0,
    with four places' worth of motion) and not at all inside; a cross-fade between group ends keeps less than the
    originals at every place inside the group."""
    frames, clips, labeler = drives
    same = motion_through(labeler, frames, frames, clips)["heading_kept_by_group_place"]
    assert same == pytest.approx([1.0] * 4)
    held = [_by_group(v, lambda t: 4 * -(-t // 4)) for v in frames]          # frames 1-4 show 4, 5-8 show 8, ...
    jump = motion_through(labeler, frames, held, clips)
    places = jump["heading_kept_by_group_place"]
    assert places[0] > 2.5 and max(abs(p) for p in places[1:]) < 0.2, places
    assert jump["heading_kept"] > 0.6, jump                                   # the whole turn is still there
    assert "by the frame's place in its 4-frame latent group" in format_vae_eval(
        {"psnr_db": {"mean": 30.0, "per_clip_min": 29.0}, "ssim": {"mean": 0.9}, "clips": 5, "motion": jump})
    fade = [np.stack([v[t] if t % 4 == 0 else
                      ((1 - (t % 4) / 4) * v[t - t % 4].astype(np.float32)
                       + (t % 4) / 4 * v[min(t - t % 4 + 4, len(v) - 1)]).round().astype(np.uint8)
                      for t in range(len(v))]) for v in frames]
    faded = motion_through(labeler, frames, fade, clips)["heading_kept_by_group_place"]
    assert max(faded) < 0.8, faded


def test_heading_by_place_refuses_clips_that_do_not_match():
    from resim.eval.vae_eval import heading_kept_by_group_place
    with pytest.raises(ValueError, match="one of each per clip"):
        heading_kept_by_group_place([np.zeros(40)], [np.zeros(40)] * 2, 9, np.array([True]))
    assert heading_kept_by_group_place([np.ones(40)], [np.ones(40)], 9, np.array([False])) == [None] * 4


def test_paired_difference_of_two_vaes_on_the_same_clips(drives):
    """--against: the VAE that blurs minus the one that freezes the motion keeps clearly more of the heading, with
    a paired interval above 0; reports read on other clips are refused."""
    frames, clips, labeler = drives
    blurred = [np.stack([cv2.GaussianBlur(f, (0, 0), 1.0) for f in v]) for v in frames]
    frozen = [np.stack([v[min(i, 12)] for i in range(len(v))]) for v in frames]
    blur = {"psnr_db": {"per_clip": [30.0, 31.0, 29.0, 30.5, 30.0]}, "motion": motion_through(labeler, frames, blurred, clips)}
    lost = {"psnr_db": {"per_clip": [31.0, 32.0, 30.0, 31.5, 31.0]}, "motion": motion_through(labeler, frames, frozen, clips)}
    d = paired_vae_difference(blur, lost)
    assert d["psnr_db"]["difference"] == pytest.approx(-1.0) and d["psnr_db"]["ci95"] == pytest.approx([-1.0, -1.0])
    assert d["heading_kept"]["difference"] > 0.6 and d["heading_kept"]["ci95"][0] > 0.3, d
    assert d["labeler_on_reconstructions"]["difference"] == pytest.approx(0.8)       # 5/5 against 1/5 right
    assert "heading kept" in format_vae_difference(d, "lost/vae.json")
    other = {**lost, "psnr_db": {"per_clip": [31.0] * 4}}
    with pytest.raises(ValueError, match="different clips"):
        paired_vae_difference(blur, other)
    mirrored = [v[:, :, ::-1] for v in frames]                                       # the originals read otherwise
    elsewhere = {**lost, "motion": motion_through(labeler, mirrored, frozen, clips)}
    with pytest.raises(ValueError, match="same clips"):
        paired_vae_difference(blur, elsewhere)


@pytest.mark.slow
def test_eval_vae_reports_motion_through_the_shipped_vae(tmp_path, capsys):
    heldout = REPO / "tests" / "data" / "synth-heldout"
    assert main(["eval", "vae", "--vae", "synth-vae", "--shards", str(heldout), "--out", str(tmp_path),
                 "--limit", "2", "--device", "cpu"]) == 0
    rep = json.loads((tmp_path / "vae.json").read_text())
    m = rep["motion"]
    assert m["clips"] == 2 and m["labeler_on_originals"]["n"] == 2 and 0 <= m["same_label"] <= 1
    assert "motion: flow-labeler accuracy on originals" in capsys.readouterr().out
    # --against: a missing report fails before the evaluation; the same VAE against itself differs by nothing
    args = ["eval", "vae", "--vae", "synth-vae", "--shards", str(heldout), "--limit", "2", "--device", "cpu"]
    with pytest.raises(SystemExit, match="--against .*missing.json"):
        main([*args, "--out", str(tmp_path / "b"), "--against", str(tmp_path / "missing.json")])
    assert main([*args, "--out", str(tmp_path / "b"), "--against", str(tmp_path / "vae.json")]) == 0
    d = json.loads((tmp_path / "b" / "vae.json").read_text())["against"]
    assert d["psnr_db"]["difference"] == pytest.approx(0.0, abs=1e-9) and d["clips"] == 2
    assert "against" in capsys.readouterr().out


def test_the_group_end_reading_sees_through_a_cross_fade_inside_each_group(drives):
    frames, clips, labeler = drives
    # what the synthetic world's decoder draws: the group ends in place, a cross-fade between them
    faded = []
    for v in frames:
        f = v.astype(np.float32).copy()
        for a in range(0, len(v) - 4, 4):
            for j in range(1, 4):
                f[a + j] = (1 - j / 4) * v[a] + j / 4 * v[a + 4]
        faded.append(f.round().astype(np.uint8))
    rep = motion_through(labeler, frames, faded, clips, group_ends=True)
    assert rep["heading_kept"] < 0.5, rep["heading_kept"]                  # the labeler, as it reads a rollout
    g = rep["group_ends"]
    assert g["heading_kept"] > 0.8 and g["originals_heading_kept"] > 0.8, g
    assert g["labeler_on_reconstructions"]["accuracy"] == 1.0
    assert "group-end reading" in format_vae_eval({"psnr_db": {"mean": 30.0, "per_clip_min": 29.0},
                                                    "ssim": {"mean": 0.9}, "clips": 5, "motion": rep})
    assert "group_ends" not in motion_through(labeler, frames, faded, clips)
