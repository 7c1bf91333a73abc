"""``TrainableWorldModel.flops_per_sample`` against torch's own FLOP counter (the MFU numerator)."""
import torch
from torch.utils.flop_counter import FlopCounterMode

from resim.train.tasks.world_model import build_world

_LINEAR_OPS = {"mm", "addmm"}


def _block_linear_forward_flops(model, t: int, h: int, w: int) -> float:
    c = model.cfg
    x = torch.randn(1, t, c.in_channels, h, w)
    text = torch.randn(1, c.max_text_seq_length, c.text_embed_dim)
    with FlopCounterMode(display=False) as fc:      # (grad enabled: its module tracker needs it)
        model(x, torch.full((1, t), 500), text)
    total = 0.0
    for name, ops in fc.get_flop_counts().items():
        if name.split(".")[-2:-1] == ["transformer_blocks"]:       # "...transformer_blocks.<i>" only
            total += sum(v for op, v in ops.items() if str(op).split(".")[1] in _LINEAR_OPS)
    return total


def test_flops_per_sample_matches_counted_block_matmuls():
    torch.manual_seed(0)
    model = build_world({"preset": "small"})
    c = model.cfg
    t, h, w = 4, 8, 12
    s = model.tokens_per_sample(latent_thw=(t, h, w))
    attention = 12.0 * c.num_layers * s * s * c.hidden_dim
    linear = model.flops_per_sample(latent_thw=(t, h, w)) - attention
    counted = 3.0 * _block_linear_forward_flops(model, t, h, w)        # forward + backward = 3 x forward
    # the formula counts biases (1 FLOP pair per output) that the counter does not: < 1 % here
    assert abs(linear - counted) / counted < 0.01, (linear, counted)
