"""``decode_latents`` with an even number of latent frames: the padding frame it appends must not change the
decoded real frames (it used to share the last decode batch's GroupNorm statistics with them)."""
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.sample.outputs import decode_latents

VAE_DIR = Path(__file__).resolve().parents[2] / "configs/models/placeholder-cogvideox-vae-tiny"


def _vae(tiled: bool):
    from resim.media.encoders import VideoVAE
    vae = VideoVAE(VAE_DIR, device="cpu")
    if tiled:  # 2x2-latent tiles: the decode goes through diffusers' tiled_decode (a decoder run per tile)
        vae.model.enable_tiling(tile_sample_min_height=16, tile_sample_min_width=16)
    return vae


@pytest.fixture(scope="module")
def vaes():
    torch.set_num_threads(1)
    return {False: _vae(False), True: _vae(True)}


def _latents(b: int, t: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(b, t, 16, 4, 6, generator=torch.Generator().manual_seed(seed))


def _decode_with_padding(vae, z, padding, **kw) -> np.ndarray:
    """``decode_latents`` with the padding frame (the last latent frame of what it hands the VAE) replaced."""
    orig = vae.model.decode

    def decode(zz, *a, **k):
        assert zz.shape[2] == z.shape[1] + 1     # even T: T + 1 frames go to the VAE, the last is the padding
        zz = zz.clone()
        zz[:, :, -1] = padding(zz[:, :, -1])
        return orig(zz, *a, **k)

    vae.model.decode = decode
    try:
        return decode_latents(vae, z, **kw)
    finally:
        del vae.model.decode                    # back to the class method


PADDINGS = {
    "zeros": torch.zeros_like,
    "large": lambda p: 6.0 * torch.randn(p.shape, generator=torch.Generator().manual_seed(1)).to(p),
    "negated": lambda p: -p,
    "nan": lambda p: torch.full_like(p, float("nan")),   # anything reaching a real frame would show
}


@pytest.mark.parametrize("tiled", [False, True])
@pytest.mark.parametrize("t", [2, 4, 6])   # 2: the padding shares the first (3-frame) batch with frames 0 and 1
def test_even_length_decode_does_not_depend_on_padding(vaes, t, tiled):
    vae = vaes[tiled]
    z = _latents(1, t)
    ref = decode_latents(vae, z)
    assert ref.shape[:2] == (1, 1 + 4 * (t - 1)) and ref.shape[-1] == 3   # (tiny tiles change H, W: diffusers')
    for name, pad in PADDINGS.items():
        np.testing.assert_array_equal(_decode_with_padding(vae, z, pad), ref, err_msg=f"padding {name}")


def test_batched_decode_does_not_depend_on_padding(vaes):
    vae = vaes[False]
    z = _latents(3, 4, seed=2)
    ref = decode_latents(vae, z, batch_size=2)       # one VAE call for 2 samples (diffusers' slicing off)
    np.testing.assert_array_equal(_decode_with_padding(vae, z, PADDINGS["large"], batch_size=2), ref)
    # one sample per call: the same frames up to the summation order of a batched convolution (1 uint8 level)
    d = np.abs(decode_latents(vae, z, batch_size=1).astype(int) - ref.astype(int))
    assert d.max() <= 1 and (d > 0).mean() < 1e-3, (d.max(), (d > 0).mean())


def test_batch_size_is_one_decoder_call_despite_slicing(vaes):
    """VideoVAE turns diffusers' slicing on (encoder memory); decode_latents' batch_size must still be what one
    VAE call decodes (slicing would split it into a decode per sample), and slicing is back on afterwards."""
    vae = vaes[False]
    assert vae.model.use_slicing
    sizes = []
    hook = vae.model.decoder.register_forward_pre_hook(lambda m, a: sizes.append(a[0].shape[0]))
    try:
        decode_latents(vae, _latents(3, 3), batch_size=2)
    finally:
        hook.remove()
    assert sizes == [2, 1]                 # 2 samples in one call, then the third
    assert vae.model.use_slicing


@pytest.mark.parametrize("tiled", [False, True])
def test_odd_length_is_diffusers_decode_and_even_prefix_matches_it(vaes, tiled):
    vae = vaes[tiled]
    z = _latents(1, 6, seed=3)
    odd = decode_latents(vae, z[:, :5])
    with torch.inference_mode():
        x = vae.model.decode((z[:, :5] / vae.info.scaling_factor).permute(0, 2, 1, 3, 4)).sample
    direct = ((x.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 4, 1).numpy()
    np.testing.assert_array_equal(odd, direct)
    even = decode_latents(vae, z)
    # every batch before the one holding the padding is diffusers' decode of the first T - 1 frames
    np.testing.assert_array_equal(even[:, :odd.shape[1]], odd)
    # nothing stays hooked into the VAE
    assert not vae.model.decoder._forward_pre_hooks
    assert not any(m._forward_hooks for m in vae.model.decoder.modules())


def test_unknown_decode_batching_is_refused(vaes):
    vae = vaes[False]
    z = _latents(1, 4)
    vae.model.num_latent_frames_batch_size = 4
    try:
        with pytest.raises(ValueError, match="2-frame decode batches"):
            decode_latents(vae, z)
        decode_latents(vae, z[:, :3])   # odd T needs no padding, so nothing to check
    finally:
        vae.model.num_latent_frames_batch_size = 2
