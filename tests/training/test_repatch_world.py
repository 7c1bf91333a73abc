"""lab/repatch_world.py: resizing a world model's 2 x 2 patches to 1 x 1 keeps what the coarse layers compute."""
import importlib.util
from pathlib import Path

import torch

from resim.models.world.config import preset
from resim.models.world.dit import WorldModel

SCRIPT = Path(__file__).resolve().parents[2] / "lab" / "repatch_world.py"


def _repatch():
    spec = importlib.util.spec_from_file_location("repatch_world", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.repatch


def test_fine_tokens_of_uniform_blocks_embed_as_the_coarse_token_and_predict_its_blocks_mean():
    torch.manual_seed(0)
    coarse = WorldModel(preset("tiny")).eval()
    fine = WorldModel(preset("tiny", patch_size=1)).eval()
    # every tensor but the two resized ones has the same shape, so a strict load checks nothing else changed
    fine.load_state_dict(_repatch()(coarse.state_dict()), strict=True)
    for k, v in coarse.state_dict().items():
        if not k.startswith(("patch_embed.proj.", "proj_out.")):
            assert torch.equal(v, fine.state_dict()[k]), k

    c = coarse.cfg.in_channels
    x = torch.randn(2, 3, c, 4, 6)                                   # (B, T, C, h, w) coarse latents
    x_up = x.repeat_interleave(2, dim=3).repeat_interleave(2, dim=4)  # each 2 x 2 block uniform
    with torch.no_grad():
        tok_c = coarse.patch_embed.video(x_up).reshape(2, 3, 4, 6, -1)   # (B, T, h/2, w/2, D)
        tok_f = fine.patch_embed.video(x_up).reshape(2, 3, 8, 12, -1)    # (B, T, h, w, D)
        # bias counted once per token on both sides: all four fine tokens of block (i, j) equal the coarse one
        assert torch.allclose(tok_f, tok_c.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3), atol=1e-5)

        h = torch.randn(5, coarse.cfg.num_attention_heads * coarse.cfg.attention_head_dim)
        out_c = coarse.proj_out(h).reshape(5, c, 2, 2)              # rows ordered (C, p, p), as unpatchify reads
        out_f = fine.proj_out(h)                                    # (5, C)
        assert torch.allclose(out_f, out_c.mean(dim=(2, 3)), atol=1e-5)
        # the rows grouped the other way, (p, p, C), average other weights: the check above tells the orders apart
        assert not torch.allclose(out_f, coarse.proj_out(h).reshape(5, 4, c).mean(1), atol=1e-3)
