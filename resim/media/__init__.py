"""Leaf package shared by the pipeline, labeling and training: video files (probe, sampled reader), the frozen
encoders (CogVideoX VAE, T5), clip geometry, the device resolver. Imports nothing of resim's own, so all sides
depend on it and not on each other."""
