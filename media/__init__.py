"""Leaf package shared by the pipeline and training: the frozen encoders (CogVideoX VAE, T5). Imports nothing
of resim's own, so both sides depend on it and not on each other."""
