"""Typed config of the diffusion objective. Torch-free."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from resim.config import ConfigError


@dataclass
class ScheduleConfig:
    """CogVideoX's training schedule (``CogVideoXDDIMScheduler`` of THUDM/CogVideoX-2b).

    ``num_train_timesteps`` (N) is the number of noise levels, ``t ∈ [0, N)``: the objective, the sampler
    (DDIM timesteps, ``history_noise_level``), the model's ``text_timestep_value`` and the loss logs all read it
    from here. CogVideoX was trained with N = 1000; a pretrained CogVideoX refuses another N (``dit.py``)."""
    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    snr_shift_scale: float = 3.0
    rescale_zero_terminal_snr: bool = True

    def __post_init__(self) -> None:
        if not 0 < self.beta_start < self.beta_end < 1:
            raise ConfigError("schedule: need 0 < beta_start < beta_end < 1")
        if self.num_train_timesteps < 2 or self.snr_shift_scale <= 0:
            raise ConfigError("schedule: num_train_timesteps >= 2 and snr_shift_scale > 0")

    @property
    def max_level(self) -> int:
        """The noisiest level, ``N - 1`` (ᾱ = 0 with ``rescale_zero_terminal_snr``)."""
        return self.num_train_timesteps - 1


@dataclass
class ObjectiveConfig:
    """How ``training_losses`` noises a clip, which conditions it drops, and where the loss counts.

    noise_mode:
      * ``diffusion_forcing`` – an independent uniform level per latent frame (Vid2World Sec. 4.1);
        loss on every frame.
      * ``resim_cond_aug`` – one level ``t_aug`` for the ``num_history_frames`` history frames (sampled in
        ``[0, cond_aug_max_t]``) and one ``t`` for the future frames (ReSim App. B.2); loss on the future only.
      * ``uniform`` – one level for all frames (full-sequence, as CogVideoX was trained); loss on every frame.
    """
    noise_mode: Literal["diffusion_forcing", "resim_cond_aug", "uniform"] = "diffusion_forcing"
    num_history_frames: int = 1          # latent frames of context (resim_cond_aug; also the loss mask there)
    cond_aug_max_t: Optional[int] = None # t_aug ~ U{0, …, cond_aug_max_t}; None: num_train_timesteps - 1
    text_drop_prob: float = 0.5          # command dropped → the prefix-only prompt (null_text) is used
    # control experiment (ReSim's controllability claim needs one): each sample's prompt is replaced by the prompt
    # of a random other sample of the batch, so the command says nothing about the future. A model trained so
    # must not follow commands; if `resim eval commands` still reads them, the metric reads something else.
    shuffle_commands: bool = False
    trajectory_drop_prob: float = 0.5    # trajectory → null embedding ...
    trajectory_keep_sources: tuple[str, ...] = ("carla",)   # ... except for these sources (always kept)
    action_drop_prob: float = 0.2        # each frame's action independently → null action
    actions_from_trajectory: bool = True # derive per-frame actions from the trajectory when the batch has none
    latent_frame_dt_s: float = 0.4       # duration of one latent frame (4 pixel frames at 10 Hz)
    # mixed datasets: a NAVSIM clip at 2 Hz is 1 + 8 frames = 3 latent frames (1 of history, 2 s each),
    # an OpenDV clip 9 + 40 = 13 (3 of history, 0.4 s each). When a batch states its clip geometry
    # (``Batch.num_history_latent_frames`` / ``latent_frame_dt_s``, from the shard metadata) it wins over
    # ``num_history_frames`` / ``latent_frame_dt_s`` above, which stay the fallback for batches without it.
    geometry_from_batch: bool = True
    waypoint_dt_s: float = 0.5
    # where the future's level is drawn: with probability ``low_level_fraction`` from U{0..low_level_max_t} instead
    # of U{0..N-1}. Under CogVideoX's SNR-shifted schedule the levels above SNR ~3 (t < 100 of 1000) are 10 % of a
    # uniform draw, yet that is where a small model's one-step prediction loses the fine detail the flow labeler reads
    # a turn from (docs/lab/2026-11-26-synth-world-stage-chain.md, finding 3); 0 (default) = the papers' uniform draw.
    low_level_fraction: float = 0.0
    low_level_max_t: int = 150
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)

    def __post_init__(self) -> None:
        for name in ("text_drop_prob", "trajectory_drop_prob", "action_drop_prob"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"objective.{name}={v} not in [0, 1]")
        if self.num_history_frames < 0:
            raise ConfigError("objective.num_history_frames must be >= 0")
        n = self.schedule.num_train_timesteps
        if self.cond_aug_max_t is not None and not 0 <= self.cond_aug_max_t < n:
            raise ConfigError(f"objective.cond_aug_max_t={self.cond_aug_max_t} must be in [0, num_train_timesteps "
                              f"= {n}) (or null: {n - 1})")
        if not 0.0 <= self.low_level_fraction <= 1.0:
            raise ConfigError(f"objective.low_level_fraction={self.low_level_fraction} not in [0, 1]")
        if self.low_level_fraction > 0 and not 0 <= self.low_level_max_t < n:   # unused at 0: any schedule's N
            raise ConfigError(f"objective.low_level_max_t={self.low_level_max_t} must be in [0, num_train_timesteps "
                              f"= {n})")
        # durations: actions_from_trajectory divides spans of latent_frame_dt_s by waypoint_dt_s; a zero or
        # negative one gives invalid (all-null) or time-reversed actions without an error
        for name in ("latent_frame_dt_s", "waypoint_dt_s"):
            v = getattr(self, name)
            if not v > 0:
                raise ConfigError(f"objective.{name}={v} must be > 0 (seconds)")

    @property
    def cond_aug_max_level(self) -> int:
        """``cond_aug_max_t`` resolved: the highest history level ``resim_cond_aug`` draws."""
        return self.schedule.max_level if self.cond_aug_max_t is None else self.cond_aug_max_t
