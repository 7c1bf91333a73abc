"""Sampling from the world model: DDIM, guidance, chunked/causal rollout with a KV cache, outputs, planning."""
