"""Typed config of the Ray pipeline (`resim pipeline run CONFIG`), validated before any work starts.

Sections (one dataclass each; units in field names):

* ``sources``  which layouts to read (``opendv``, ``navsim``, ``carla``) and/or a ``synthetic`` world;
* ``clip``     clip geometry (ReSim: 10 Hz, 9 history + 40 future frames) and the window stride;
* ``labels``   optical-flow and trajectory labelling knobs (turn threshold, flow resolution);
* ``balance``  ReSim's turn balance: windows extracted ``turn_factor`` x more densely in turning segments;
* ``dedup``    near-duplicate clips across the dataset; ``quality`` per-clip quality filters (off by default);
* ``encode``   resolution, VAE + T5 folders (placeholders by default), dtype, slicing/tiling;
* ``shards``   shard size limits and the shard prefix;
* ``quarantine`` retry policy for items that fail;
* ``ray``      where to run and the resources of every stage, declared once here.

Every error names the dotted key (``clip.stride_frames: ...``); paths that must exist, every reader's own
options and a reused synthetic world are checked by ``resim.pipeline.load.check_paths`` before Ray starts
(``resim.pipeline.load.load_config`` = this module's dataclasses + those checks; the checks build the readers, which
import this module, so they live apart).
``--set key.sub=value`` overrides any value (YAML-parsed). Relative paths are relative to the working
directory and are made absolute on load (:func:`absolute_paths`), so the config a run saves, ships to its
workers and hashes names the data it read wherever it is read from.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, Optional

from resim.config import ConfigError, check_positive, from_dict, to_dict
from resim.labeling.config import CutConfig, LabelerConfig, StillConfig
from resim.shards.schema import ClipSpec
from resim.shards.split import SplitConfig
from resim.shipped import shipped_dir, shipped_model

REPO_ROOT = Path(__file__).resolve().parents[2]


PLACEHOLDER_VAE = shipped_dir("placeholder-cogvideox-vae-tiny")
PLACEHOLDER_T5 = shipped_dir("placeholder-t5-tiny")


def _max_items(value: Optional[int]) -> None:
    # A negative cap would slice items[:-1], i.e. silently drop the last item instead of capping.
    if value is not None and value < 0:
        raise ConfigError(f"max_items must be >= 0 or null (no cap), got {value}")


# ---------------------------------------------------------------------------------------------- clip
@dataclass
class ClipConfig:
    """Clip geometry. ReSim: 10 Hz, 9 history + 40 future frames (49 = 1 + 4 x 12 for the causal VAE)."""

    fps_hz: float = 10.0
    num_history_frames: int = 9
    num_future_frames: int = 40
    stride_frames: int = 20                   # start-to-start distance of straight-driving windows
    num_waypoints: int = 8
    waypoint_dt_s: float = 0.5
    # An episode shorter than one clip by at most this many frames (at fps_hz) still gives one clip, from
    # its start, with its last frame held to the clip's length; 0: such an episode is quarantined (too
    # short). For outcome-labelled routes: a CARLA / synthetic route ends ~2 s after a crash, so the
    # shortest routes are the early-crash hazards, the clips a reward model (ReSim's Video2Reward) most needs.
    max_held_frames: int = 0

    def __post_init__(self):
        check_positive("fps_hz", self.fps_hz)
        check_positive("stride_frames", self.stride_frames)
        if not isinstance(self.max_held_frames, int) or isinstance(self.max_held_frames, bool) \
                or not 0 <= self.max_held_frames < self.num_frames:
            raise ConfigError(f"max_held_frames must be an integer in [0, num_frames - 1 = {self.num_frames - 1}] "
                              f"(at least one recorded frame per clip), got {self.max_held_frames!r}")
        check_positive("num_waypoints", self.num_waypoints)
        check_positive("waypoint_dt_s", self.waypoint_dt_s)
        if self.num_history_frames < 1 or self.num_future_frames < 1:
            raise ConfigError("num_history_frames and num_future_frames must be >= 1")
        horizon_s = self.num_waypoints * self.waypoint_dt_s
        if horizon_s > self.num_future_frames / self.fps_hz + 1e-9:
            raise ConfigError(f"num_waypoints x waypoint_dt_s = {horizon_s} s exceeds the future window "
                              f"{self.num_future_frames / self.fps_hz} s")

    @property
    def num_frames(self) -> int:
        return self.num_history_frames + self.num_future_frames

    def spec(self) -> ClipSpec:
        return ClipSpec(fps_hz=self.fps_hz, num_history_frames=self.num_history_frames,
                        num_future_frames=self.num_future_frames, num_waypoints=self.num_waypoints,
                        waypoint_dt_s=self.waypoint_dt_s)


# ------------------------------------------------------------------------------------------- sources
@dataclass
class OpenDVSource:
    """OpenDV-YouTube style: a folder of long dashcam videos (mp4/webm/mkv), resampled to clip.fps_hz.

    ReSim discards the first 90 s and last 60 s of every video (intros, outros) and keeps >= 720p videos.
    """

    root: Optional[Path] = None               # null: source disabled
    start_discard_s: float = 90.0
    end_discard_s: float = 60.0
    min_height_px: int = 720
    max_items: Optional[int] = None           # cap for smoke runs
    clip: Optional[ClipConfig] = None         # per-source clip geometry (null: the top-level `clip`)

    def __post_init__(self):
        check_positive("start_discard_s", self.start_discard_s, allow_zero=True)
        check_positive("end_discard_s", self.end_discard_s, allow_zero=True)
        check_positive("min_height_px", self.min_height_px)
        _max_items(self.max_items)


@dataclass
class NavsimSource:
    """NAVSIM / OpenScene: ``navsim_logs/<split>/<log>.pkl`` + ``sensor_blobs/<split>/<log>/CAM_F0``."""

    root: Optional[Path] = None
    split: str = "mini"
    camera: str = "CAM_F0"
    max_items: Optional[int] = None
    clip: Optional[ClipConfig] = None         # NAVSIM logs are 2 Hz: a 10 Hz clip cannot be cut from them

    def __post_init__(self):
        _max_items(self.max_items)


@dataclass
class CarlaSource:
    """Bench2Drive-style CARLA episodes (``anno/*.json.gz`` + ``camera/rgb_front``), with route outcomes."""

    root: Optional[Path] = None
    camera: str = "rgb_front"
    max_items: Optional[int] = None
    clip: Optional[ClipConfig] = None

    def __post_init__(self):
        _max_items(self.max_items)


@dataclass
class SyntheticSource:
    """A synthetic world (``resim synth``) in the three real layouts, read back through the real readers.

    Generated into ``root`` when ``root`` has no ``ground_truth`` file yet (reused otherwise).
    """

    root: Optional[Path] = None               # null: disabled; relative paths are relative to the CWD
    episodes: int = 6
    seed: int = 0
    layouts: tuple[str, ...] = ("opendv", "navsim", "carla")
    clip: dict[str, ClipConfig] = field(default_factory=dict)   # per-layout clip geometry overrides
    preset: str = "demo"                      # resim synth preset (demo: 128x224, 16 s episodes)
    # share of the episodes made as counterfactual triples: one history, then left / straight / right at a
    # junction (docs/sources.md, "Counterfactual forks"); 0 = none
    fork_fraction: float = 0.0
    # share made as pace-fork triples: one history, then the expert at 0.5 / 1 / 1.5 times its speed, CARLA layout
    # (docs/sources.md, "Pace forks"); 0 = none
    pace_fork_fraction: float = 0.0

    def __post_init__(self):
        check_positive("episodes", self.episodes)
        if not 0 <= self.fork_fraction <= 1:
            raise ConfigError(f"fork_fraction must be in [0, 1], got {self.fork_fraction}")
        if not 0 <= self.pace_fork_fraction <= 1 or self.fork_fraction + self.pace_fork_fraction > 1:
            raise ConfigError(f"pace_fork_fraction must be in [0, 1 - fork_fraction], got {self.pace_fork_fraction}")
        bad = [x for x in list(self.layouts) + list(self.clip) if x not in ("opendv", "navsim", "carla")]
        if bad:
            raise ConfigError(f"layouts: unknown layout {bad[0]!r} (known: opendv, navsim, carla)")
        # a layout listed twice would enumerate every item twice (two units with one id)
        dup = sorted({x for x in self.layouts if list(self.layouts).count(x) > 1})
        if dup:
            raise ConfigError(f"layouts: {dup[0]!r} is listed more than once")
        if not self.layouts:
            raise ConfigError("layouts: empty (list at least one of opendv, navsim, carla, "
                              "or set sources.synthetic.root: null to disable the synthetic world)")


@dataclass
class SourcesConfig:
    opendv: OpenDVSource = field(default_factory=OpenDVSource)
    navsim: NavsimSource = field(default_factory=NavsimSource)
    carla: CarlaSource = field(default_factory=CarlaSource)
    synthetic: SyntheticSource = field(default_factory=SyntheticSource)


# -------------------------------------------------------------------------------------------- labels
@dataclass
class LabelsConfig:
    """Command labelling. Flow runs on every clip; the trajectory command where poses exist.

    ``labeler`` is ``resim.labeling.config.LabelerConfig`` itself (flow estimator + command rules), so every
    labeler knob is a config key here: ``labels.labeler.command.turn_threshold_deg``,
    ``labels.labeler.flow.work_width_px``, ...
    """

    labeler: LabelerConfig = field(default_factory=LabelerConfig)
    prefer: Literal["trajectory", "flow"] = "trajectory"   # which command wins where both exist
    cuts: CutConfig = field(default_factory=CutConfig)     # scene cuts: no clip spans one (resim/labeling/cuts.py)
    still: StillConfig = field(default_factory=StillConfig)  # standing still: tagged, dropped or kept


# --------------------------------------------------------------------------------------------- dedup
@dataclass
class DedupConfig:
    """Near-duplicate clips across the dataset (``resim/pipeline/dedup.py``): one pass after every unit committed."""

    enabled: bool = True
    max_bits: int = 16           # of the 256-bit signature: a copy on the same window grid 0-few (re-encoded);
    #                              the same road a few frames or seconds apart 16-40; other footage 87-116
    band_bits: int = 8           # LSH band width (8 or 16): 16 checks ~256x fewer pairs on large datasets

    def __post_init__(self):
        if not 0 <= self.max_bits <= 128:
            raise ConfigError(f"dedup.max_bits must be in [0, 128], got {self.max_bits}")
        if self.band_bits not in (8, 16):
            raise ConfigError(f"dedup.band_bits must be 8 or 16, got {self.band_bits}")


# ------------------------------------------------------------------------------------------- quality
@dataclass
class QualityConfig:
    """Per-clip quality filters (``resim/pipeline/clip_quality.py``): a window outside a bound is dropped before the VAE
    (a ``dropped`` quarantine row naming the column). Every bound is off (null) by default: the columns are
    written for every clip, so choose bounds from a dataset's distributions (``resim shards stats DIR --plot``).
    Values are measured at ``encode.height_px`` x ``encode.width_px``; sharpness depends on that size."""

    min_luma_mean_8bit: Optional[float] = None    # e.g. 25: night footage too dark to read
    max_luma_mean_8bit: Optional[float] = None    # e.g. 235: blown out
    min_luma_std_8bit: Optional[float] = None     # e.g. 12: fog, glare, a lens cap
    min_sharpness_lapvar: Optional[float] = None  # blur; 8-bit levels^2 at the encode size
    max_static_edge_frac: Optional[float] = None  # e.g. 0.1: dashboard, bonnet or overlays in view
    min_flow_quality: Optional[float] = None      # 0..1: the labeler's fit kept too few points to trust its command

    def __post_init__(self):
        for name in ("min_luma_mean_8bit", "max_luma_mean_8bit", "min_luma_std_8bit", "min_sharpness_lapvar",
                     "max_static_edge_frac", "min_flow_quality"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"quality.{name} must be a finite number >= 0 or null (off), got {v!r}")
        for name in ("max_static_edge_frac", "min_flow_quality"):
            if (getattr(self, name) or 0) > 1:
                raise ConfigError(f"quality.{name} is a share in [0, 1], got {getattr(self, name)}")
        for name in ("min_luma_mean_8bit", "max_luma_mean_8bit", "min_luma_std_8bit"):
            if (getattr(self, name) or 0) > 255:
                raise ConfigError(f"quality.{name} is in 8-bit levels (0..255), got {getattr(self, name)}")
        lo, hi = self.min_luma_mean_8bit, self.max_luma_mean_8bit
        if lo is not None and hi is not None and lo >= hi:
            raise ConfigError(f"quality.min_luma_mean_8bit ({lo}) must be below quality.max_luma_mean_8bit ({hi})")

    @property
    def enabled(self) -> bool:
        return any(v is not None for v in vars(self).values())


# ------------------------------------------------------------------------------------------- balance
@dataclass
class BalanceConfig:
    """ReSim's turn balance: turning windows are extracted ``turn_factor`` x more densely (distinct,
    overlapping windows at stride ``clip.stride_frames / turn_factor``), never byte copies."""

    enabled: bool = True
    turn_factor: int = 5

    def __post_init__(self):
        check_positive("turn_factor", self.turn_factor)


# -------------------------------------------------------------------------------------------- encode
@dataclass
class EncodeConfig:
    """Resize/crop + CogVideoX VAE + T5. Null model folders = the shipped tiny random placeholders."""

    height_px: int = 64                       # VAE input (ReSim stages: 256x448 then 512x896)
    width_px: int = 96
    frames_height_px: int = 64                # frames.mp4 (low-res pixels for reward/metrics/previews)
    frames_width_px: int = 96
    vae: Optional[Path] = None                # local folder (a diffusers VAE or a pipeline with vae/)
    text_encoder: Optional[Path] = None       # local folder (T5 + tokenizer, or a pipeline with both)
    placeholder_seed: int = 0                 # weights of placeholder models when a folder has none
    max_text_tokens: int = 226                # CogVideoX was trained with 226 padded T5 tokens
    dtype: Literal["float32", "float16", "bfloat16"] = "float32"   # compute dtype of the VAE
    latent_dtype: Literal["float16", "bfloat16"] = "float16"       # stored dtype
    vae_slicing: bool = True
    vae_tiling: bool = True
    batch_size: int = 1                       # clips per VAE forward
    torch_threads: int = 1                    # per CPU encode actor (one Ray CPU each)

    def __post_init__(self):
        for k in ("height_px", "width_px", "frames_height_px", "frames_width_px"):
            v = getattr(self, k)
            if v <= 0 or v % 8:
                raise ConfigError(f"{k} must be a positive multiple of 8 (VAE downsamples 8x), got {v}")
        check_positive("batch_size", self.batch_size)
        check_positive("max_text_tokens", self.max_text_tokens)
        check_positive("torch_threads", self.torch_threads)

    @property
    def vae_path(self) -> Path:
        return shipped_model(self.vae) if self.vae is not None else shipped_dir(PLACEHOLDER_VAE.name)

    def vae_temporal_compression(self) -> int | None:
        """The VAE's temporal ratio from its config.json (a component folder or a pipeline folder with vae/),
        without loading it; None when the folder is not on this machine (the encode stage then says so)."""
        for f in (self.vae_path / "vae" / "config.json", self.vae_path / "config.json"):
            if f.is_file():
                try:
                    return int(json.loads(f.read_text()).get("temporal_compression_ratio", 4))
                except (OSError, ValueError, TypeError) as e:
                    raise ConfigError(f"encode.vae: {f} is not a readable VAE config ({e})") from None
        return None

    @property
    def text_encoder_path(self) -> Path:
        return (shipped_model(self.text_encoder) if self.text_encoder is not None
                else shipped_dir(PLACEHOLDER_T5.name))


# -------------------------------------------------------------------------------------------- shards
@dataclass
class ShardsConfig:
    max_samples_per_shard: int = 1000
    max_bytes_per_shard: int = 1 << 30

    def __post_init__(self):
        # checked here, not only by the shard writer: a bad limit must fail at load, before any work
        for k in ("max_samples_per_shard", "max_bytes_per_shard"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{k} must be >= 1, got {getattr(self, k)}")


@dataclass
class QuarantineConfig:
    """Bad input goes to ``quarantine/*.parquet``; transient I/O errors are retried first."""

    max_attempts: int = 2                     # tries for OSError (I/O) before quarantining; SourceError: 1
    retry_quarantined: bool = False           # on rerun, try quarantined units again (attempts += 1)

    def __post_init__(self):
        check_positive("max_attempts", self.max_attempts)


# ----------------------------------------------------------------------------------------------- ray
@dataclass
class StageResources:
    """Resources of one stage's actor pool (declared once here, used by the Ray runner)."""

    actors: int = 1
    num_cpus: float = 1.0
    num_gpus: float | Literal["auto"] = 0.0   # "auto": 1 per actor when the cluster has GPUs, else 0
    memory_gib: float = 0.0                   # reserved per actor (Ray's `memory`); 0: no reservation

    def __post_init__(self):
        check_positive("actors", self.actors)
        check_positive("num_cpus", self.num_cpus, allow_zero=True)
        if self.num_gpus != "auto":
            check_positive("num_gpus", float(self.num_gpus), allow_zero=True)
        check_positive("memory_gib", self.memory_gib, allow_zero=True)

    @property
    def memory_bytes(self) -> int | None:
        """Ray's ``memory`` argument (whole bytes), None where nothing is reserved."""
        return int(self.memory_gib * (1 << 30)) or None


def _res(actors=1, num_cpus=1.0, num_gpus=0.0):
    return lambda: StageResources(actors=actors, num_cpus=num_cpus, num_gpus=num_gpus)


@dataclass
class StagesResources:
    cut: StageResources = field(default_factory=_res(1, 0.25))
    label: StageResources = field(default_factory=_res(1, 0.5))
    balance: StageResources = field(default_factory=_res(1, 0.1))
    encode: StageResources = field(default_factory=_res(1, 1.0, "auto"))
    prompts: StageResources = field(default_factory=_res(1, 0.5, "auto"))
    write: StageResources = field(default_factory=_res(1, 0.25))


@dataclass
class RayConfig:
    """Where the job runs. ``address: null`` starts an embedded local Ray (``num_cpus`` of this machine)."""

    address: Optional[str] = None             # "auto" or "HOST:6379" to join a running cluster
    num_cpus: Optional[int] = None            # embedded Ray only; null = all cores
    executor: Literal["ray", "local"] = "ray" # "local": same stages, sequential, no Ray (debugging, tests)
    progress_bars: bool = True
    fuse_cpu_stages: bool = True              # cut+label+balance in one actor pool (label's resources)
    stages: StagesResources = field(default_factory=StagesResources)

    def __post_init__(self):
        if self.num_cpus is not None and self.num_cpus < 1:
            raise ConfigError(f"num_cpus must be >= 1 or null (all cores), got {self.num_cpus}")


# ------------------------------------------------------------------------------------------ pipeline
@dataclass
class PipelineConfig:
    out: Optional[Path] = None                # output dataset folder (or --out)
    sources: SourcesConfig = field(default_factory=SourcesConfig)
    clip: ClipConfig = field(default_factory=ClipConfig)
    labels: LabelsConfig = field(default_factory=LabelsConfig)
    balance: BalanceConfig = field(default_factory=BalanceConfig)
    dedup: DedupConfig = field(default_factory=DedupConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)
    encode: EncodeConfig = field(default_factory=EncodeConfig)
    shards: ShardsConfig = field(default_factory=ShardsConfig)
    quarantine: QuarantineConfig = field(default_factory=QuarantineConfig)
    # the train / held-out split by episode, written to OUT/split.json at the end of each run (not hashed: it
    # changes no sample, and a rerun rewrites it)
    split: SplitConfig = field(default_factory=SplitConfig)
    ray: RayConfig = field(default_factory=RayConfig)

    def __post_init__(self):
        tc = self.encode.vae_temporal_compression()
        for key, clip in self.clip_configs():
            if tc and (clip.num_frames - 1) % tc:
                raise ConfigError(
                    f"{key}: num_history_frames + num_future_frames - 1 = {clip.num_frames - 1} must be divisible "
                    f"by the VAE's temporal compression {tc} (a causal video VAE keeps frame 0 alone, then "
                    f"encodes {tc} frames per latent frame)")
            if self.balance.enabled and clip.stride_frames % self.balance.turn_factor:
                raise ConfigError(
                    f"balance.turn_factor: {key}.stride_frames ({clip.stride_frames}) must be divisible by "
                    f"balance.turn_factor ({self.balance.turn_factor}) so turning windows lie on a finer grid")
            future_s = clip.num_future_frames / clip.fps_hz
            if abs(self.labels.labeler.command.window_s - future_s) > 1e-6:
                raise ConfigError(
                    f"labels.labeler.command.window_s ({self.labels.labeler.command.window_s}) must equal the "
                    f"future window of {key} ({key}.num_future_frames / fps_hz = {future_s:g} s)")
        if abs(self.labels.labeler.flow.sample_hz - self.clip.fps_hz) > 1e-9:
            raise ConfigError(f"labels.labeler.flow.sample_hz ({self.labels.labeler.flow.sample_hz}) must equal "
                              f"clip.fps_hz ({self.clip.fps_hz}): flow runs on the clip-rate frames")
        if not any((self.sources.opendv.root, self.sources.navsim.root, self.sources.carla.root,
                    self.sources.synthetic.root)):
            raise ConfigError("sources: no source configured (set sources.<kind>.root for at least one of "
                              "opendv, navsim, carla, synthetic)")

    def clip_configs(self) -> list[tuple[str, ClipConfig]]:
        """Every clip geometry in use, with its config key (top level + per-source overrides)."""
        out = [("clip", self.clip)]
        for kind in ("opendv", "navsim", "carla"):
            c = getattr(self.sources, kind).clip
            if c is not None:
                out.append((f"sources.{kind}.clip", c))
        out += [(f"sources.synthetic.clip.{k}", c) for k, c in self.sources.synthetic.clip.items()]
        return out

    def fine_stride_frames(self, clip: ClipConfig | None = None) -> int:
        """Start-to-start distance of turning windows (stride / factor)."""
        clip = clip or self.clip
        if not self.balance.enabled:
            return clip.stride_frames
        return clip.stride_frames // self.balance.turn_factor


def _absolute(p: Optional[Path]) -> Optional[Path]:
    # abspath, not resolve(): no symlink is followed, so a path already absolute is left as it is on every
    # machine (Ray workers re-derive the data hash from it; a node with other symlinks must get the same)
    return None if p is None else Path(os.path.abspath(os.path.expanduser(str(p))))


def _model_path(p: Optional[Path]) -> Optional[Path]:
    """A model folder made absolute, except a shipped model's bare name (``synth-vae``): a name is the same
    model in every checkout, so the saved config and the data hash stay valid where the repository moves."""
    if p is not None and shipped_model(p) != Path(p):
        return Path(p)
    return _absolute(p)


def absolute_paths(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with every path (``out``, each ``sources.*.root``, ``encode.vae`` / ``text_encoder``) made
    absolute against the working directory; idempotent, null stays null (placeholder models, disabled sources).

    Applied on load, by the runner and by the data hash, so the saved ``OUT/config.yaml`` says which data was
    read, the hash does not depend on how a path was spelled (``data/x`` vs ``/repo/data/x``, or rerunning
    from ``OUT/config.yaml``), and the same relative config run from another folder is another config.
    """
    s = cfg.sources
    sources = replace(s, opendv=replace(s.opendv, root=_absolute(s.opendv.root)),
                      navsim=replace(s.navsim, root=_absolute(s.navsim.root)),
                      carla=replace(s.carla, root=_absolute(s.carla.root)),
                      synthetic=replace(s.synthetic, root=_absolute(s.synthetic.root)))
    enc = replace(cfg.encode, vae=_model_path(cfg.encode.vae), text_encoder=_model_path(cfg.encode.text_encoder))
    return replace(cfg, out=_absolute(cfg.out), sources=sources, encode=enc)


def config_from_dict(data: dict) -> PipelineConfig:
    """Rebuild a config shipped to Ray actors as a plain dict (no path checks: they ran on the driver)."""
    return from_dict(PipelineConfig, data)


__all__ = ["PipelineConfig", "absolute_paths", "config_from_dict", "to_dict", "ConfigError"]
