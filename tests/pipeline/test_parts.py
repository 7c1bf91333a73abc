"""Pure parts of the pipeline: window geometry, balance selection, encoders, quarantine table."""
import numpy as np
import pytest

from resim.media.frames import center_crop, cover_size, rate_step, sliding_windows
from resim.pipeline.stages.balance import select_windows

from .conftest import REPO


def test_cover_and_crop_keep_aspect():
    assert cover_size((720, 1280), (256, 448)) == (256, 456)     # 16:9 covers 7:4 with a small crop
    assert cover_size((900, 1600), (64, 96)) == (64, 114)
    img = np.zeros((64, 114, 3), np.uint8)
    assert center_crop(img, (64, 96)).shape == (64, 96, 3)


def test_rate_step():
    assert rate_step(10.0, 10.0) == 1 and rate_step(20.0, 10.0) == 2 and rate_step(29.97, 10.0) == 3
    assert rate_step(2.0, 10.0) is None and rate_step(15.0, 10.0) is None


def test_sliding_windows_one_pass_overlapping():
    frames = (np.full((2, 2, 3), i, np.uint8) for i in range(10, 30))   # clip indices 10..29
    got = list(sliding_windows(frames, 10, [10, 12, 13, 20], 5))
    assert [s for s, _ in got] == [10, 12, 13, 20]
    for s, w in got:
        assert w.shape == (5, 2, 2, 3) and list(w[:, 0, 0, 0]) == list(range(s, s + 5))
    short = list(sliding_windows((np.zeros((1, 1, 3), np.uint8) for _ in range(6)), 0, [0, 4], 5))
    assert [s for s, _ in short] == [0]                                 # frames ran out: caller sees 1 of 2


def test_balance_is_denser_in_turns_never_copies():
    # 100 candidate starts on a fine grid of 4 (stride 20, factor 5); frames 200..300 are a turn
    wins = [{"start": s, "is_turning": 200 <= s < 300} for s in range(0, 400, 4)]
    kept, counts = select_windows(wins, 20, 5, True)
    starts = [w["start"] for w in kept]
    assert len(set(starts)) == len(starts)                              # distinct windows only
    assert counts["before"] == {"clips": 20, "turning": 5}
    assert counts["after"] == {"clips": 15 + 25, "turning": 25}         # 5x the turning windows
    assert all(w["balance_weight"] == (5.0 if w["is_turning"] else 1.0) for w in kept)
    share_before = counts["before"]["turning"] / counts["before"]["clips"]
    share_after = counts["after"]["turning"] / counts["after"]["clips"]
    assert share_after == pytest.approx(5 * share_before / (5 * share_before + 1 - share_before))
    kept_off, c_off = select_windows([w for w in wins if w["start"] % 20 == 0], 20, 5, False)
    assert c_off["after"] == c_off["before"]


def test_placeholder_encoders_are_deterministic_and_flagged():
    import torch

    from resim.media.encoders import TextEncoder, VideoVAE

    torch.set_num_threads(1)
    vae_dir = REPO / "configs/models/placeholder-cogvideox-vae-tiny"
    x = np.random.default_rng(0).integers(0, 255, (1, 9, 32, 48, 3), dtype=np.uint8)
    a = VideoVAE(vae_dir, tiling=False)
    z = a.encode(x, [7])
    assert z.shape == (1, 3, 16, 4, 6) and a.info.placeholder and a.info.vae_id == vae_dir.name
    assert np.array_equal(z, VideoVAE(vae_dir).encode(x, [7]))          # seeded weights + seeded noise
    assert not np.array_equal(z, a.encode(x, [8]))
    # the sample is mean + std * noise, times the scaling factor
    with torch.no_grad():
        d = a.model.encode(torch.from_numpy(x).permute(0, 4, 1, 2, 3).float() / 127.5 - 1).latent_dist
    mean = d.mean[0].permute(1, 0, 2, 3).numpy() * a.info.scaling_factor
    assert np.abs(z[0] - mean).mean() < 3 * a.info.scaling_factor * float(d.std.mean())

    t5 = TextEncoder(REPO / "configs/models/placeholder-t5-tiny")
    e = t5.encode(["Turning left.", "Turning right."])
    assert e.shape == (2, 226, t5.info.dim) and t5.info.placeholder
    assert not np.allclose(e[0], e[1])


def test_prompt_table_records_each_prompts_unpadded_token_count(tmp_path):
    """num_tokens is the prompt's own token count (attention-mask sum), not the padded length (226)."""
    from resim.pipeline.stages.prompts import PromptStage, all_prompts
    from resim.shards.prompts import PromptTable
    from resim.shards.schema import prompt_id

    from .conftest import make_config

    cfg = make_config(tmp_path / "out")
    stage = PromptStage(cfg, device="cpu")
    texts = [t for t, _ in all_prompts()]
    stage({"text": texts, "role": [r for _, r in all_prompts()]})
    entries = PromptTable(tmp_path / "out").entries()
    want = [len(stage.encoder.tokenizer(t).input_ids) for t in texts]   # no padding asked: the real length
    got = [entries[prompt_id(t)]["num_tokens"] for t in texts]
    assert got == want
    assert all(0 < n < cfg.encode.max_text_tokens for n in got)
    assert len(set(got)) > 1                                          # different prompts, different counts
    null, left = prompt_id(texts[-1]), prompt_id(next(t for t in texts if t.endswith("Turning left.")))
    assert entries[null]["num_tokens"] < entries[left]["num_tokens"]  # the bare prefix is shorter
    assert entries[null]["shape"][0] == cfg.encode.max_text_tokens   # the stored embedding stays padded


def test_quarantine_table_roundtrip(tmp_path):
    from resim.pipeline import quarantine

    st = {"item_id": "a/b.mp4", "unit_id": "u1", "origin": "opendv", "attempts": 1, "quarantine": [],
          "status": "ok"}
    quarantine.quarantine_unit(st, "cut", "too short: 3 frames")
    quarantine.drop_window(st, "label", 40, "NaN poses")
    quarantine.write_rows(tmp_path, "u1", st["quarantine"])
    rows = quarantine.read_table(tmp_path)
    assert st["status"] == "quarantined"
    assert [(r["item"], r["stage"], r["status"]) for r in rows] == [
        ("a/b.mp4", "cut", "quarantined"), ("a/b.mp4#f0000040", "label", "dropped")]
    assert set(rows[0]) == set(quarantine.QUARANTINE_COLUMNS)
