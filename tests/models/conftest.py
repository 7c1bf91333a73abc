"""Fixtures for the world-model tests: a tiny random diffusers CogVideoX and a tiny WorldModel."""
import pytest
import torch

TINY_COGVIDEOX = dict(num_attention_heads=2, attention_head_dim=16, in_channels=16, out_channels=16,
                      time_embed_dim=32, text_embed_dim=64, num_layers=2, sample_width=12, sample_height=8,
                      sample_frames=49, patch_size=2, max_text_seq_length=16)


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    """Every test of tests/models on one torch thread (tests/conftest.py)."""
    yield


@pytest.fixture
def cogvideox():
    """A random-init tiny diffusers CogVideoXTransformer3DModel (weights jittered so no layer is trivially 0)."""
    from diffusers import CogVideoXTransformer3DModel
    torch.manual_seed(0)
    m = CogVideoXTransformer3DModel(**TINY_COGVIDEOX).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    return m


def randomize_new_modules(model, std=0.1):
    """Give the zero-initialised outputs/null embeddings of the new modules non-zero values (tests only)."""
    with torch.no_grad():
        for n, p in model.named_parameters():
            if n.startswith(("trajectory_encoder.head", "trajectory_encoder.null",
                             "action_encoder.proj_out", "action_encoder.null")):
                p.normal_(0, std)
    return model


@pytest.fixture
def tiny_model():
    from resim.models.world.config import preset
    from resim.models.world.dit import WorldModel
    torch.manual_seed(1)
    return randomize_new_modules(WorldModel(preset("tiny"))).eval()
