"""Video2Reward (ReSim appendix B.2): DINOv2 per frame + spatio-temporal head -> scalar reward.

Light module: import the pieces from their files (model, features, data, metrics, score, train).
"""
