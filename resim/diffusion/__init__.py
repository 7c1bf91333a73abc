"""The world model's diffusion objective: schedule, v-targets, noise-level sampling, training_losses."""
from resim.diffusion.config import ObjectiveConfig, ScheduleConfig
from resim.diffusion.losses import training_losses

__all__ = ["ObjectiveConfig", "ScheduleConfig", "training_losses"]
