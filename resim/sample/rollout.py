"""Chunked, guided, autoregressive rollout of the world model, with a history KV cache.

One **round** starts from a window of ``history_frames`` latent frames (ReSim: the last 9 pixel frames = 3
latent frames) and generates ``frames_per_round`` latent frames (ReSim: 10 = 40 pixel frames = 4 s at 10 Hz)
under that round's condition (prompt, trajectory). Inside a round the new frames are generated in **chunks**
of ``chunk_frames`` latent frames, each denoised together by DDIM while every earlier frame of the window is
fed as (clean or lightly noised) history:

* ``chunk_frames = frames_per_round`` reproduces ReSim (all 10 future frames denoised jointly);
* ``chunk_frames = 1`` reproduces Vid2World's frame-by-frame autoregressive rollout.

The next round's window is the last ``history_frames`` frames of everything so far (sliding window), so any
horizon can be reached. The window slides in *latent* space (ReSim re-encodes the last 9 decoded pixel
frames; with CogVideoX's causal VAE that differs slightly, and costs a decode + encode per round).

**History noise** (Diffusion Forcing / Vid2World App. C: "a small noise added to history frames"): a frame
entering the history is noised ONCE to level ``history_noise_level`` (0 = clean, the default) and fed with
that level; it is not re-noised at every step, so its keys/values stay constant while a chunk is denoised.

**KV cache.** With a causal model (block-causal mask: a frame's tokens never see later frames, text tokens see
only text) the keys/values of the text and the history frames do not change while a chunk is denoised. So per
round we run the window's history once with ``return_kv_cache=True`` and then feed only the chunk's frames at
every DDIM step (``kv_cache=cache``); after a chunk is done it is appended to the cache with one more forward
of just that chunk. Without the cache every step re-runs history + chunk. Both give the same frames (tests).
A new round rebuilds the cache: the window has slid (positions are absolute within the window) and the
prompt/trajectory may have changed (the trajectory embedding is added to every frame's tokens).

**Guidance** (see ``guidance.py``): when enabled, every forward carries 2B samples, ``[conditional;
unconditional]``, and the cache holds both halves. Actions derived from the trajectory (``actions_from_trajectory``:
the CLI's ``--actions-from-trajectory`` policy) are trajectory information: where the unconditional branch drops
the trajectory it drops them too (null action on every frame whose action was derived), as training's condition
dropout always drops derived actions together with the trajectory (``resim.diffusion.losses``).

Model interface (``resim.models.world.dit.WorldModel``): ``model(x, t, text, trajectory=None, actions=None, *,
trajectory_keep=None, action_keep=None, kv_cache=None, return_kv_cache=False) -> v``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Literal, Sequence

import torch

from resim.config import ConfigError
from resim.diffusion.ddim import DDIMSchedule, cogvideox_alphas_cumprod, ddim_step, forward_noise
from resim.diffusion.guidance import GuidanceConfig, combine_branches


@dataclass
class RolloutConfig:
    """How to sample. Frame counts are *latent* frames (CogVideoX: 1 latent frame = 4 pixel frames)."""
    num_steps: int = 50                    # DDIM steps per chunk (ReSim: 50); <= the model's num_train_timesteps
    history_frames: int = 3                # window kept at each round start (ReSim: 9 px frames = 3 latent)
    frames_per_round: int = 10             # latent frames per round (ReSim: 10 = 40 px = 4 s at 10 Hz)
    chunk_frames: int = 10                 # denoised together: frames_per_round = ReSim, 1 = Vid2World
    history_noise_level: int = 0           # level history frames are noised to (once) and fed at; 0 = clean;
                                           # < the model's num_train_timesteps
    kv_cache: Literal["auto", "on", "off"] = "auto"   # auto: on for causal models
    guidance: GuidanceConfig = field(default_factory=GuidanceConfig)
    include_levels: tuple[int, ...] = ()   # further noise levels every chunk's DDIM run stops at (a distilled
                                           # student's levels, where the teacher's trajectory is recorded)

    def __post_init__(self) -> None:
        # upper bounds depend on the model's schedule: check_schedule, at the start of every rollout
        if self.num_steps < 1:
            raise ConfigError(f"num_steps={self.num_steps} must be >= 1")
        if self.history_frames < 1:
            raise ConfigError("history_frames must be >= 1 (the rollout is conditioned on observed frames)")
        if self.frames_per_round < 1 or not 1 <= self.chunk_frames <= self.frames_per_round:
            raise ConfigError(f"need 1 <= chunk_frames ({self.chunk_frames}) <= frames_per_round "
                              f"({self.frames_per_round})")
        if self.history_noise_level < 0:
            raise ConfigError(f"history_noise_level={self.history_noise_level} must be >= 0")
        if any(int(t) < 0 for t in self.include_levels):
            raise ConfigError(f"include_levels={list(self.include_levels)} must be >= 0")

    def check_schedule(self, num_train_timesteps: int) -> None:
        """The steps and levels this config asks for must exist in a schedule of ``num_train_timesteps`` levels
        (the run's ``model.objective.schedule``; CogVideoX: 1000)."""
        n = int(num_train_timesteps)
        if self.num_steps > n:
            raise ConfigError(f"num_steps={self.num_steps} > the model's num_train_timesteps={n} "
                              f"(DDIM steps are distinct noise levels: at most {n})")
        if self.history_noise_level >= n:
            raise ConfigError(f"history_noise_level={self.history_noise_level} not in [0, {n}) "
                              f"(the model's num_train_timesteps={n})")
        if any(int(t) >= n for t in self.include_levels):
            raise ConfigError(f"include_levels={list(self.include_levels)} not all in [0, {n}) "
                              f"(the model's num_train_timesteps={n})")


ROLLOUT_PRESETS: dict[str, dict] = {
    "resim": dict(num_steps=50, history_frames=3, frames_per_round=10, chunk_frames=10, history_noise_level=0),
    # Vid2World: frame by frame; a context of 3 + up to 9 generated frames inside each 10-frame round
    "vid2world": dict(num_steps=50, history_frames=3, frames_per_round=10, chunk_frames=1, history_noise_level=0),
}


@dataclass
class Condition:
    """One round's conditioning. ``text``/``null_text``: T5 embeddings ``(B, L, D_text)`` of the prompt (prefix +
    command) and of the prefix alone (the CFG null prompt); ``trajectory``: ``(B, 8, 3)`` or None (null)."""
    text: torch.Tensor
    null_text: torch.Tensor | None = None
    trajectory: torch.Tensor | None = None
    label: str = ""                        # e.g. the command, for outputs


@dataclass
class PolicyInput:
    """What a policy callback sees before each chunk (closed-loop driving inside the model)."""
    latents: torch.Tensor                  # (B, T_so_far, C, h, w) float32: initial history + generated frames
    frame_index: int                       # absolute index (in ``latents``' time axis) of the first frame to make
    num_frames: int                        # frames in this chunk; return actions (B, num_frames, A)
    round_index: int
    condition: Condition


# returns the chunk's actions (B, c, A), or (actions, valid (B, c) bool): valid False → the model's null action
# (e.g. frames past the end of the trajectory the actions are derived from)
Policy = Callable[[PolicyInput], "torch.Tensor | tuple[torch.Tensor, torch.Tensor]"]


@dataclass
class RolloutResult:
    latents: torch.Tensor                  # (B, H0 + F, C, h, w) float32: the given history then F generated frames
    num_history_frames: int                # H0
    actions: torch.Tensor | None           # (B, H0 + F, A) actions used (history: given or zeros), or None
    action_valid: torch.Tensor | None      # (B, H0 + F) bool: False where the null action was fed
    round_labels: list[str]
    kv_cache_used: bool
    model_forwards: int                    # number of model calls (each one batched over both CFG branches)
    seconds: float

    @property
    def future(self) -> torch.Tensor:
        return self.latents[:, self.num_history_frames:]


def _model_causal(model: Any) -> bool:
    cfg = getattr(model, "cfg", None)
    return bool(getattr(cfg, "causal", getattr(model, "causal", False)))


def _model_dtype(model: Any) -> torch.dtype:
    for p in model.parameters():
        return p.dtype
    return torch.float32


def ddim_schedule(cfg: RolloutConfig, schedule: Any = None) -> DDIMSchedule:
    """The DDIM steps of ``cfg`` over the noise schedule the model was trained with: ``schedule`` is the run's
    ``model.objective.schedule`` (``resim.diffusion.config.ScheduleConfig``, read from its saved config by
    ``resim.sample.load.run_objective``), None = CogVideoX's; checked first with :meth:`RolloutConfig.check_schedule`."""
    ac = cogvideox_alphas_cumprod(schedule)
    cfg.check_schedule(int(ac.shape[0]))
    return DDIMSchedule(cfg.num_steps, ac, include=cfg.include_levels)


def rollout_num_steps_total(cfg: RolloutConfig, num_future_frames: int, schedule: Any = None) -> int:
    """DDIM steps a rollout takes (for a progress bar): steps × number of chunks over all rounds (``schedule``:
    the model's, as for :func:`rollout`)."""
    chunks, left = 0, num_future_frames
    while left > 0:
        in_round = min(cfg.frames_per_round, left)
        chunks += math.ceil(in_round / cfg.chunk_frames)
        left -= in_round
    return chunks * len(ddim_schedule(cfg, schedule))


def rollout_num_future_frames(seconds: float, fps_hz: float = 10.0, temporal_compression: int = 4) -> int:
    """Latent frames needed for ``seconds`` of future video: ``ceil(seconds * fps / 4)`` (4 s → 10)."""
    if seconds <= 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    return math.ceil(round(seconds * fps_hz, 6) / temporal_compression)


class _Roller:
    """State of one rollout; see :func:`rollout` (split out to keep each method about one thing)."""

    def __init__(self, model, history, cfg: RolloutConfig, generator, history_actions, use_cache, progress,
                 same_noise: bool = False, actions_from_trajectory: bool = False, schedule: Any = None,
                 on_step: "Callable[[torch.Tensor, Any], None] | None" = None,
                 generators: "Sequence[torch.Generator] | None" = None):
        self.model, self.cfg, self.gen = model, cfg, generator
        self.gens = generators   # one per batch element (``seeds``), else None: the batch shares ``generator``
        self.on_step = on_step
        self.same_noise = same_noise
        self.device, self.mdtype = history.device, _model_dtype(model)
        self.schedule = ddim_schedule(cfg, schedule)
        self.latents = history.float()                         # (B, T, C, h, w), grows
        # the fed version of each frame (noised once to history_noise_level when it became history)
        self.fed = self._noise_history(self.latents)
        self.actions: torch.Tensor | None = None      # (B, T, A) float32, grows with latents
        self.action_valid: torch.Tensor | None = None  # (B, T) bool; False → the model's null action
        # (B, T) bool: the frame's action was derived from the trajectory (the generated frames' actions when
        # actions_from_trajectory; given history actions never are)
        self.action_derived: torch.Tensor | None = None
        self.actions_from_trajectory = actions_from_trajectory
        if history_actions is not None:
            if tuple(history_actions.shape[:2]) != tuple(history.shape[:2]):
                raise ValueError(f"history_actions must be (B, H0, A) with (B, H0) = {tuple(history.shape[:2])}, "
                                 f"got {tuple(history_actions.shape)}")
            self.actions = history_actions.float().to(self.device)
            self.action_valid = torch.ones(history.shape[:2], dtype=torch.bool, device=self.device)
            self.action_derived = torch.zeros(history.shape[:2], dtype=torch.bool, device=self.device)
        self.use_cache = use_cache
        self.guided = cfg.guidance.enabled
        self.scales = cfg.guidance.scales(len(self.schedule))
        self.forwards = 0
        self.progress = progress

    def add_actions(self, chunk_actions: torch.Tensor | None, new: int, valid: torch.Tensor | None = None) -> None:
        """Append the next chunk's actions (None → null action for those frames; ``valid`` (B, new) bool: False
        → null action for that frame)."""
        b, t = self.latents.shape[:2]
        if chunk_actions is None and self.actions is None:
            return
        if self.actions is None:   # first actions seen: the history frames get the null action
            self.actions = torch.zeros(b, t, chunk_actions.shape[-1], device=self.device)
            self.action_valid = torch.zeros(b, t, dtype=torch.bool, device=self.device)
            self.action_derived = torch.zeros(b, t, dtype=torch.bool, device=self.device)
        if chunk_actions is None:
            chunk_actions = torch.zeros(b, new, self.actions.shape[-1], device=self.device)
            valid = torch.zeros(b, new, dtype=torch.bool, device=self.device)
        elif valid is None:
            valid = torch.ones(b, new, dtype=torch.bool, device=self.device)
        elif tuple(valid.shape) != (b, new) or valid.dtype != torch.bool:
            raise ValueError(f"action valid mask must be bool (B, {new}) = ({b}, {new}), got "
                             f"{valid.dtype} {tuple(valid.shape)}")
        if chunk_actions.shape[-1] != self.actions.shape[-1]:
            raise ValueError(f"action dim changed: {self.actions.shape[-1]} then {chunk_actions.shape[-1]}")
        valid = valid.to(self.device)
        chunk_actions = torch.where(valid[..., None], chunk_actions.float().to(self.device), 0.0)
        self.actions = torch.cat([self.actions, chunk_actions], dim=1)
        self.action_valid = torch.cat([self.action_valid, valid], dim=1)
        derived = valid & self.actions_from_trajectory
        self.action_derived = torch.cat([self.action_derived, derived], dim=1)

    # -- helpers -------------------------------------------------------------------------------------------
    def _randn(self, shape) -> torch.Tensor:
        # drawn on CPU so a seed gives the same noise on every device; with same_noise the batch shares one
        # draw (common random numbers: planning compares candidates that differ only in their condition)
        if self.same_noise:
            one = torch.randn((1,) + tuple(shape[1:]), generator=self.gen, dtype=torch.float32)
            return one.expand(tuple(shape)).contiguous().to(self.device)
        if self.gens is not None:   # each element's draws depend on its own seed alone, not on its batch
            return torch.stack([torch.randn(tuple(shape[1:]), generator=g, dtype=torch.float32)
                                for g in self.gens]).to(self.device)
        return torch.randn(shape, generator=self.gen, dtype=torch.float32).to(self.device)

    def _noise_history(self, x: torch.Tensor) -> torch.Tensor:
        lvl = self.cfg.history_noise_level
        if lvl == 0:
            return x
        return forward_noise(x, self._randn(x.shape), float(self.schedule.alpha(lvl)))

    def _two(self, x: torch.Tensor | None) -> torch.Tensor | None:
        return None if x is None or not self.guided else torch.cat([x, x])

    def _branch_inputs(self, cond: Condition, window: slice, new: int):
        """Batched text/trajectory/actions (+ keep masks) for the window's frames, the last ``new`` being generated."""
        g = self.cfg.guidance
        b = self.latents.shape[0]
        text = cond.text
        if self.guided:
            if g.drop_text and cond.null_text is None:
                raise ValueError("guidance drops the text command but the condition has no null_text "
                                 "(the prefix-only prompt embedding)")
            text = torch.cat([cond.text, cond.null_text if g.drop_text else cond.text])
        traj, traj_keep = cond.trajectory, None
        if traj is not None and self.guided:
            traj = torch.cat([traj, traj])
            keep_u = torch.zeros(b, dtype=torch.bool) if g.drop_trajectory else torch.ones(b, dtype=torch.bool)
            traj_keep = torch.cat([torch.ones(b, dtype=torch.bool), keep_u]).to(self.device)
        acts, act_keep = self._window_actions(window, new)
        return text, traj, traj_keep, acts, act_keep

    def _window_actions(self, window: slice, new: int):
        """Actions + keep masks of the window's frames (both branches when guided), the last ``new`` generated."""
        if self.actions is None:
            return None, None
        g = self.cfg.guidance
        acts, act_keep = self.actions[:, window], self.action_valid[:, window]
        if not self.guided:
            return acts, act_keep
        keep_u = act_keep.clone()
        if g.drop_recent_actions and new:   # Vid2World causal action guidance: the newest action(s) masked
            keep_u[:, -new:] = False
        if g.drop_trajectory:
            # actions derived from a trajectory carry it: a branch without the trajectory must not see them
            # (training drops derived actions with the trajectory, so "trajectory dropped, derived actions kept"
            # is an input the model never saw)
            keep_u &= ~self.action_derived[:, window]
        return torch.cat([acts, acts]), torch.cat([act_keep, keep_u])

    def _call(self, x, t, text, traj, traj_keep, acts, act_keep, cache=None, return_cache=False):
        self.forwards += 1
        kw: dict[str, Any] = {}
        if traj_keep is not None:
            kw["trajectory_keep"] = traj_keep
        if act_keep is not None:
            kw["action_keep"] = act_keep
        if cache is not None:
            kw["kv_cache"] = cache
        if return_cache:
            kw["return_kv_cache"] = True
        return self.model(x.to(self.mdtype), t, text.to(self.mdtype) if text is not None else None,
                          traj, acts, **kw)

    # -- one chunk -----------------------------------------------------------------------------------------
    def chunk(self, cond: Condition, win_start: int, new: int, cache):
        """Denoise ``new`` frames after the window ``[win_start, T)``; returns (frames (B,new,...), cache)."""
        b, t_now = self.latents.shape[:2]
        shape = (b, new) + tuple(self.latents.shape[2:])
        nb = 2 * b if self.guided else b
        ctx = self.fed[:, win_start:]
        n_ctx = ctx.shape[1]
        lvl_hist = self.cfg.history_noise_level
        t_hist = torch.full((nb, n_ctx), lvl_hist, dtype=torch.long, device=self.device)
        text, traj, traj_keep, acts, act_keep = self._branch_inputs(cond, slice(win_start, t_now + new), new)
        if self.use_cache and cache is None:   # history keys/values: once per round
            hist_acts = acts[:, :n_ctx] if acts is not None else None
            hist_keep = act_keep[:, :n_ctx] if act_keep is not None else None
            _, cache = self._call(self._two(ctx) if self.guided else ctx, t_hist, text, traj, traj_keep,
                                  hist_acts, hist_keep, return_cache=True)
        x = self._randn(shape)
        for step in self.schedule:
            if self.on_step is not None:
                self.on_step(x, step)
            t_new = torch.full((nb, new), step.t, dtype=torch.long, device=self.device)
            x_in = self._two(x) if self.guided else x
            if self.use_cache:
                v = self._call(x_in, t_new, None, traj, traj_keep,
                               acts[:, n_ctx:] if acts is not None else None,
                               act_keep[:, n_ctx:] if act_keep is not None else None, cache=cache)
            else:
                full = torch.cat([self._two(ctx) if self.guided else ctx, x_in], dim=1)
                v = self._call(full, torch.cat([t_hist, t_new], dim=1), text, traj, traj_keep, acts, act_keep)
                v = v[:, n_ctx:]
            v = v.float()
            if self.guided:
                v = combine_branches(v, self.scales[step.index], self.cfg.guidance.rescale_phi)
            x, _ = ddim_step(x, v, step.a_t, step.a_prev)
            if self.progress is not None:
                self.progress.update(1)
        return x, cache

    def append(self, frames: torch.Tensor, cond: Condition, cache, extend_cache: bool):
        """Add finished frames to the state; with the cache on, extend it by their (history-level) keys/values
        (one forward of just these frames; the last chunk of a round skips it, the next round rebuilds)."""
        fed = self._noise_history(frames)
        self.latents = torch.cat([self.latents, frames], dim=1)
        self.fed = torch.cat([self.fed, fed], dim=1)
        if not (self.use_cache and extend_cache):
            return cache
        n = fed.shape[1]
        nb = fed.shape[0] * (2 if self.guided else 1)
        t_hist = torch.full((nb, n), self.cfg.history_noise_level, dtype=torch.long, device=self.device)
        text, traj, traj_keep, _, _ = self._branch_inputs(cond, slice(0, 0), 0)
        # the appended frames are history now: as the uncached path feeds them (no "recent" masking; derived
        # actions still dropped in a branch without the trajectory)
        t_all = self.latents.shape[1]
        acts, act_keep = self._window_actions(slice(t_all - n, t_all), 0)
        _, cache = self._call(self._two(fed) if self.guided else fed, t_hist, text, traj, traj_keep,
                              acts, act_keep, cache=cache, return_cache=True)
        return cache


def rollout(model: Any, history: torch.Tensor, conditions: Condition | Sequence[Condition] | Callable[[int], Condition],
            num_future_frames: int, cfg: RolloutConfig | None = None, *, seed: int = 0,
            actions: torch.Tensor | None = None, history_actions: torch.Tensor | None = None,
            policy: Policy | None = None, progress: Any = None, same_noise: bool = False,
            actions_from_trajectory: bool = False, schedule: Any = None,
            on_step: Callable[[torch.Tensor, Any], None] | None = None,
            seeds: Sequence[int] | None = None) -> RolloutResult:
    """Roll the world model out for ``num_future_frames`` latent frames after ``history``.

    Args:
        model: the world model (see module docstring); put it in eval mode and on the device first.
        history: ``(B, H0, C, h, w)`` clean latents (VAE latents × scaling factor); the first round's window is
            the last ``cfg.history_frames`` of them.
        conditions: one :class:`Condition` for every round, a list (one per round, the last one repeats), or a
            callable ``round_index -> Condition``.
        actions: ``(B, num_future_frames, A)`` per-frame actions for the generated frames, or None;
        history_actions: ``(B, H0, A)`` actions of the history frames (None: null action there);
        policy: callback returning the actions of each chunk ``(B, c, A)``, or ``(actions, valid (B, c) bool)``
            (closed loop); excludes ``actions``.
        actions_from_trajectory: the actions (given or from the policy) are derived from each round's trajectory;
            a guidance branch that drops the trajectory then drops them too (null action), as in training.
        progress: an object with ``update(n)`` (e.g. tqdm), advanced once per DDIM step.
        same_noise: every batch element gets the same noise draws (compare conditions, not noise).
        schedule: the noise schedule the model was trained with (the run's ``model.objective.schedule``, as
            ``run_objective(checkpoint).schedule``); None = CogVideoX's (1000 levels).
        on_step: called as ``on_step(x, step)`` before every DDIM step of every chunk, with the chunk's frames
            ``x`` (B, c, C, h, w) at level ``step.t`` (a :class:`~resim.diffusion.ddim.DDIMStep`): the sampler's
            trajectory, e.g. for distillation.
        seeds: one seed per batch element instead of ``seed``: element ``i``'s noise is then the same whatever
            else is in the batch (distillation caches each clip's teacher trajectory by its key).
    Returns:
        :class:`RolloutResult` with all latents (history + generated), float32.
    """
    cfg = cfg or RolloutConfig()
    if history.dim() != 5:
        raise ValueError(f"history must be (B, H0, C, h, w), got {tuple(history.shape)}")
    if history.shape[1] < 1:
        raise ValueError("history must contain at least one latent frame")
    if num_future_frames < 1:
        raise ValueError(f"num_future_frames must be >= 1, got {num_future_frames}")
    if actions is not None and policy is not None:
        raise ValueError("give either actions or a policy, not both")
    causal = _model_causal(model)
    if cfg.kv_cache == "on" and not causal:
        raise ConfigError("kv_cache='on' needs a causal model (cfg.causal=True): without the block-causal mask "
                          "the history's keys/values depend on the frames being denoised")
    use_cache = cfg.kv_cache == "on" or (cfg.kv_cache == "auto" and causal)
    b = history.shape[0]
    if actions is not None and tuple(actions.shape[:2]) != (b, num_future_frames):
        raise ValueError(f"actions must be (B, num_future_frames, A) = ({b}, {num_future_frames}, A), "
                         f"got {tuple(actions.shape)}")
    if seeds is not None and (len(seeds) != history.shape[0] or same_noise):
        raise ValueError(f"seeds: one per batch element ({history.shape[0]}), and not with same_noise; "
                         f"got {len(seeds)}")
    gen = torch.Generator().manual_seed(seed)
    gens = None if seeds is None else [torch.Generator().manual_seed(int(s)) for s in seeds]
    r = _Roller(model, history, cfg, gen, history_actions, use_cache, progress, same_noise, actions_from_trajectory,
                schedule, on_step, gens)
    acting = actions is not None or policy is not None
    h0 = history.shape[1]
    labels: list[str] = []
    t0 = time.perf_counter()
    made = round_idx = 0
    with torch.no_grad():
        while made < num_future_frames:
            cond = _condition_for(conditions, round_idx)
            labels.append(cond.label)
            in_round = min(cfg.frames_per_round, num_future_frames - made)
            win_start = max(0, r.latents.shape[1] - cfg.history_frames)
            cache, done_in_round = None, 0
            while done_in_round < in_round:
                new = min(cfg.chunk_frames, in_round - done_in_round)
                if acting or r.actions is not None:
                    chunk_acts, chunk_valid = _chunk_actions(actions, policy, r, made, new, round_idx, cond)
                    r.add_actions(chunk_acts, new, chunk_valid)
                frames, cache = r.chunk(cond, win_start, new, cache)
                done_in_round += new
                made += new
                cache = r.append(frames, cond, cache, extend_cache=done_in_round < in_round)
            round_idx += 1
    return RolloutResult(r.latents, h0, r.actions, r.action_valid, labels, use_cache, r.forwards,
                         time.perf_counter() - t0)


def _condition_for(conditions, round_idx: int) -> Condition:
    if isinstance(conditions, Condition):
        return conditions
    if callable(conditions):
        return conditions(round_idx)
    if not conditions:
        raise ValueError("conditions is empty")
    return conditions[min(round_idx, len(conditions) - 1)]


def _chunk_actions(actions, policy, r: _Roller, made: int, new: int, round_idx: int, cond: Condition):
    """(the chunk's actions or None, their valid mask or None = all valid)."""
    if actions is not None:
        return actions[:, made:made + new], None
    if policy is not None:
        a = policy(PolicyInput(r.latents, r.latents.shape[1], new, round_idx, cond))
        valid = None
        if isinstance(a, tuple):
            a, valid = a
        if a.dim() != 3 or tuple(a.shape[:2]) != (r.latents.shape[0], new):
            raise ValueError(f"policy returned actions of shape {tuple(a.shape)}; expected (B, {new}, A)")
        return a, valid
    return None, None
