"""A dataset encoded by a per-frame VAE (temporal ratio 1) and one encoded by CogVideoX's 4x layout both go through
the pipeline, train and sample: every consumer reads the ratio from the VAE and the samples, none assumes 4."""
import json

import numpy as np
import pytest
import yaml

from tests.pipeline.conftest import REPO

from resim.cli import main
from resim.pipeline import runner
from resim.shards.reader import iter_samples
from resim.shards.schema import latent_frame_count, pixel_frame_count
from resim.shards.video import encode_mp4

# one geometry for both ratios: 2.5 Hz, 3 history + 10 future frames (13 = 1 + 4 x 3 = 1 + 1 x 12)
CLIP = ["clip.fps_hz=2.5", "labels.labeler.flow.sample_hz=2.5", "clip.num_history_frames=3",
        "clip.num_future_frames=10", "clip.num_waypoints=8", "clip.waypoint_dt_s=0.5", "clip.stride_frames=5",
        "encode.height_px=32", "encode.width_px=48", "encode.frames_height_px=32", "encode.frames_width_px=48",
        "ray.executor=local"]


def _vae_folder(tmp_path, ratio: int):
    cfg = json.loads((REPO / "configs/models/placeholder-cogvideox-vae-tiny/config.json").read_text())
    cfg["temporal_compression_ratio"] = ratio
    folder = tmp_path / f"placeholder-vae-r{ratio}"   # a seeded stand-in: only placeholder-* folders may lack weights
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(cfg))
    return folder


@pytest.mark.parametrize("ratio", [1, 4])
def test_a_dataset_of_either_temporal_ratio_encodes_trains_and_samples(config_for, tmp_path, ratio):
    vae = _vae_folder(tmp_path, ratio)
    cfg = config_for("data", *CLIP, f"encode.vae={vae}")
    runner.run(cfg)
    samples = list(iter_samples(cfg.out, decode_video=True, attach_prompts=False))
    assert {s["meta.json"]["num_frames"] for s in samples} == {13, 9}       # video clips and 2-Hz NAVSIM clips
    for s in samples:    # 13 frames: 13 latents per-frame, 4 at 4x; NAVSIM's 9: 9 or 3
        assert s["latent.npy"].shape[0] == latent_frame_count(s["meta.json"]["num_frames"], ratio)
    samples = [s for s in samples if s["meta.json"]["num_frames"] == 13]

    run = tmp_path / "run"
    assert main(["train", "world", "--preset", "tiny", "--shards", str(cfg.out), "--out", str(run), "--steps", "2",
                 "--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false",
                 "--set", "trainer.loss_curve_png=false"]) == 0
    h = latent_frame_count(3, ratio)                                         # 3 history latents, or 1 at 4x
    out = tmp_path / "sample"
    assert main(["sample", "--checkpoint", str(run), "--shards", str(cfg.out), "--history", samples[0]["__key__"],
                 "--set", f"rollout.history_frames={h}", "--command", "Turning left", "--seconds", "2", "--steps", "2",
                 "--device", "cpu", "--out", str(out)]) == 0
    future = -(-5 // ratio)                                                  # 2 s x 2.5 Hz = 5 frames
    lat = np.load(out / "sample_latents.npy")
    assert lat.shape[0] == h + future
    meta = json.loads((out / "sample_meta.json").read_text())
    assert meta["num_frames"] == pixel_frame_count(h + future, ratio)     # decoded by the dataset's own VAE
    assert meta["num_history_frames"] == pixel_frame_count(h, ratio)

    # a video file as the history: resampled to the 2.5 Hz the run recorded from its data, encoded by that VAE
    assert yaml.safe_load((run / "final" / "data_encode.yaml").read_text())["clip"]["fps_hz"] == 2.5
    video = tmp_path / "history.mp4"
    video.write_bytes(encode_mp4(np.concatenate([s["frames"] for s in samples[:2]]), 10.0))   # 26 frames
    out = tmp_path / "sample-video"
    assert main(["sample", "--checkpoint", str(run), "--history", str(video), "--set", f"rollout.history_frames={h}",
                 "--command", "Turning right", "--seconds", "2", "--steps", "2", "--device", "cpu",
                 "--out", str(out)]) == 0
    meta = json.loads((out / "sample_meta.json").read_text())
    assert meta["fps_hz"] == 2.5 and meta["num_frames"] == pixel_frame_count(h + future, ratio)


def test_the_clip_length_is_checked_against_the_vaes_own_ratio(tmp_path):
    """23 frames (3 + 20 at 5 Hz) suit a per-frame VAE; a 4x VAE cannot encode them (22 is not 4k) and says so."""
    from resim.pipeline.load import load_config
    from resim.config import ConfigError

    five_hz = ["clip.fps_hz=5", "labels.labeler.flow.sample_hz=5", "clip.num_history_frames=3",
               "clip.num_future_frames=20", "clip.stride_frames=10"]
    base = REPO / "configs/pipeline/synthetic.yaml"
    cfg = load_config(base, [*five_hz, f"encode.vae={_vae_folder(tmp_path, 1)}"], out=tmp_path / "o")
    assert cfg.clip.num_frames == 23
    with pytest.raises(ConfigError, match="clip: .* must be divisible by the VAE's temporal compression 4"):
        load_config(base, [*five_hz, f"encode.vae={_vae_folder(tmp_path, 4)}"], out=tmp_path / "o")
