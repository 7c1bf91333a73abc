"""Small real datasets for tests, benchmarks and demos of the training code (written with the real ShardWriter)."""
from __future__ import annotations

from pathlib import Path

from resim.shards.schema import COMMANDS, ClipSpec
from tests.support.shards import add_dummy_prompts, make_dummy_sample
from resim.shards.writer import ShardWriter


def navsim_spec():
    """NAVSIM-style clip geometry: 2 Hz logs, 1 history + 8 future frames = 3 latent frames (1 of history)."""
    return ClipSpec(fps_hz=2.0, num_history_frames=1, num_future_frames=8, num_waypoints=8, waypoint_dt_s=0.5)


def write_world_dataset(root, num_samples=12, per_shard=4, sources=("synthetic",), seed=0, specs=None):
    """Shards the tiny world model can train on: 16-channel 8x12 latents, (16, 64) prompt embeddings.
    Commands cycle; sources cycle per shard (one source per shard, as the pipeline writes them).
    ``specs``: optional ``{source: ClipSpec}`` (clip geometry per source; default ReSim's 9 + 40 frames
    at 10 Hz = 13 latent frames), e.g. ``{"navsim": navsim_spec()}`` for a mixed-geometry dataset."""
    add_dummy_prompts(root, seq_len=16, dim=64, seed=seed)
    n_shards = -(-num_samples // per_shard)
    i = 0
    for s in range(n_shards):
        src = sources[s % len(sources)]
        with ShardWriter(root, f"{src}-{s}", max_samples_per_shard=per_shard, config_hash="test") as w:
            for _ in range(min(per_shard, num_samples - i)):
                w.write(make_dummy_sample(source=src, item_id=f"ep-{s}-{i // 3}", start_frame=(i % 3) * 10,
                                          command=COMMANDS[i % 3], seed=seed * 1000 + i, latent_channels=16,
                                          latent_hw=(8, 12), frames_hw=(16, 24), spec=(specs or {}).get(src)))
                i += 1
    # the encode section a pipeline's config.yaml holds (the trainer copies it into RUN/final/data_encode.yaml, so
    # a sampler knows the decoder): these random latents stand for the shipped placeholder VAE's
    (Path(root) / "config.yaml").write_text("encode:\n  vae: placeholder-cogvideox-vae-tiny\n")
    return Path(root)
