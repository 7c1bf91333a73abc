"""One world-model bundle, loaded in one call (resim.sample.bundle): the README's Python example runs as written, on
the shipped synthetic-world model, and the bundle carries the model's own encoding."""
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.sample.bundle import WorldModelBundle
from resim.sample.load import SamplingInputError
from resim.shards.video import encode_mp4
from tests.support.shards import dummy_frames

README = Path(__file__).resolve().parents[2] / "README.md"


def _history_video(path: Path) -> Path:
    path.write_bytes(encode_mp4(dummy_frames(12, 64, 96, yaw_deg=8.0), 10.0))   # 1.2 s at 10 Hz
    return path


@pytest.fixture(scope="module")
def bundle():
    torch.set_num_threads(1)
    return WorldModelBundle.from_pretrained("synth-world")


def test_bundle_carries_the_models_own_encoding(bundle):
    """The VAE is the one that encoded the model's training clips (its data_encode.yaml: synth-vae), not the
    placeholder; the history size and rate are its training clips'."""
    assert bundle.vae.info.vae_id == "synth-vae" and not bundle.vae.info.placeholder
    assert bundle.size_hw == (64, 96)
    assert bundle.clip_fps_hz == pytest.approx(10.0)
    assert bundle.model.training is False


def test_rollout_from_a_video_history(bundle, tmp_path):
    video = _history_video(tmp_path / "history.mp4")
    out = bundle.rollout(video, command="Turning left", seconds=0.8, steps=2, seed=3)
    assert out.frames.dtype == np.uint8 and out.frames.shape[1:] == (64, 96, 3)
    assert out.num_history_frames_px == 9 and out.frames.shape[0] == 9 + 8      # 0.8 s at 10 Hz after the history
    assert out.latents.shape[0] == 3 + 2 and out.labels == ["Turning left"]
    again = bundle.rollout(video, command="Turning left", seconds=0.8, steps=2, seed=3)
    assert np.array_equal(out.frames, again.frames)                              # same seed and inputs, same video
    right = bundle.rollout(video, command="Turning right", seconds=0.8, steps=2, seed=3)
    assert not torch.equal(out.latents[3:], right.latents[3:])                   # the command reaches the model


def test_bad_inputs_are_one_line_errors(bundle, tmp_path):
    with pytest.raises(SamplingInputError, match="not one of"):
        bundle.rollout(_history_video(tmp_path / "h.mp4"), command="Fly", seconds=0.4, steps=1)
    with pytest.raises(SamplingInputError, match="needs the bundle loaded with shards"):
        bundle.history("some-sample-key")
    with pytest.raises(SamplingInputError):
        WorldModelBundle.from_pretrained(tmp_path / "no-such-run")


def test_a_dataset_encoded_by_another_vae_is_refused_in_one_line(tmp_path):
    """The model learnt synth-vae's latents; a dataset of the placeholder VAE's is refused, naming both."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "config.yaml").write_text("encode:\n  vae: placeholder-cogvideox-vae-tiny\n  height_px: 64\n  width_px: 96\n")
    with pytest.raises(SamplingInputError, match="encoded with the VAE placeholder-cogvideox-vae-tiny.*learnt the "
                                                 "latents of synth-vae") as e:
        WorldModelBundle.from_pretrained("synth-world", shards=data)
    assert "\n" not in str(e.value) and e.value.part == "shards"
    (data / "config.yaml").write_text("encode:\n  vae: synth-vae\n  height_px: 64\n  width_px: 96\n")
    assert WorldModelBundle.from_pretrained("synth-world", shards=data).vae.info.vae_id == "synth-vae"


def test_the_readme_python_example_runs(tmp_path, monkeypatch):
    """The README's "From Python" block, run as written in a folder holding its history.mp4."""
    text = README.read_text()
    m = re.search(r"```python\n(.*?)```", text, flags=re.S)
    assert m, "README.md has no ```python block (the bundle's example)"
    code = m.group(1)
    assert "WorldModelBundle.from_pretrained" in code
    _history_video(tmp_path / "history.mp4")
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)
    frames = scope["out"].frames
    assert frames.ndim == 4 and frames.shape[-1] == 3 and frames.shape[0] > scope["out"].num_history_frames_px


def test_a_missing_decoder_is_an_error_not_a_placeholder(tmp_path):
    """A model whose export says nothing of its VAE, or a VAE folder without weights, is refused in one line naming
    the VAE part; only the shipped placeholder-* folders are built from a seed."""
    from resim.shipped import shipped_model
    run = tmp_path / "run"
    run.mkdir()
    for f in Path(shipped_model("synth-world")).iterdir():
        if f.name != "data_encode.yaml" and f.is_file():
            (run / f.name).symlink_to(f)
    with pytest.raises(SamplingInputError, match="no file says which VAE") as e:
        WorldModelBundle.from_pretrained(run)
    assert "\n" not in str(e.value) and e.value.part == "vae"
    no_weights = tmp_path / "my-vae"
    no_weights.mkdir()
    (no_weights / "config.json").write_text((Path(shipped_model("synth-vae")) / "config.json").read_text())
    with pytest.raises(SamplingInputError, match="my-vae: config.json but no weights") as e:
        WorldModelBundle.from_pretrained("synth-world", vae=no_weights)
    assert e.value.part == "vae"
