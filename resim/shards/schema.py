"""The shard schema: every member of a training sample, with its extension,
dtype, shape, units and whether it is optional.

A clip is the unit of training data. A sample is a group of tar members that
share one ``__key__`` (WebDataset convention: ``KEY.EXT``). Defaults are
ReSim's: 10 Hz, 9 history + 40 future frames = 49 frames, which the CogVideoX
causal VAE turns into 13 latent frames (1 + 4x12); the trajectory is 8 future
waypoints at 2 Hz (0.5 s ... 4.0 s). These are defaults of ``ClipSpec``, not
constants: every consumer reads them from the sample's metadata.

Dataset layout on disk (see docs/data_format.md)::

    DIR/
      shards/<prefix>-<seq>.tar     WebDataset tars (members below)
      index/<shard>.json            per-shard index: sample count, bytes, sha256, label histogram
      manifest/<shard>.parquet      one row per sample (MANIFEST_COLUMNS)
      prompts/prompts.json          the prompt table: id -> text, role, shape, dtype, encoder
      prompts/<id>.npy              one T5 embedding per distinct prompt, stored once
      quarantine/*.parquet          items the pipeline could not use (item, stage, reason)
      config.yaml                   the resolved config that produced the dataset
      stats.json, report.png        written by the pipeline

No member is ever decoded with pickle; a shard holding a ``.pyd``/``.pickle``
member is refused (``FORBIDDEN_EXTENSIONS``).
"""
from __future__ import annotations

import dataclasses
import hashlib
import re
from dataclasses import dataclass
from typing import Any

from resim.config import ConfigError

SCHEMA_VERSION = 3
# versions a reader of this code reads: 2 added ego_motion_pct_s, stopped and signature, 3 the per-clip quality
# columns (``since`` below); an older sample simply lacks them (null in the manifest)
READABLE_SCHEMA_VERSIONS = (1, 2, 3)

SOURCES = ("opendv", "navsim", "carla", "synthetic")
COMMANDS = ("Turning left", "Moving forward", "Turning right")
COMMAND_SOURCES = ("flow", "trajectory")

# CogVideoX was trained with this prefix; ReSim joins it with the command.
PROMPT_PREFIX = (
    "This video depicts a realistic view from the driver's perspective of a car driving on the road."
)

FORBIDDEN_EXTENSIONS = ("pyd", "pickle", "pkl", "pth", "pt", "mp")  # decoders that may run code


# A causal video VAE (CogVideoX's, with any temporal ratio r) keeps frame 0 alone and compresses each following
# group of r frames into one latent frame: 1 + r k pixel frames <-> 1 + k latent frames. The ratio is the VAE's
# (4 for CogVideoX-2B, 1 for a per-frame VAE); a sample states it through num_frames and latent_shape.
def latent_frame_count(pixel_frames: int, temporal_compression: int) -> int:
    """Latent frames of ``pixel_frames`` (>= 1) through a causal VAE of ``temporal_compression``."""
    return 1 + (int(pixel_frames) - 1) // int(temporal_compression)


def pixel_frame_count(latent_frames: int, temporal_compression: int) -> int:
    """Pixel frames that ``latent_frames`` (>= 1) decode to: ``1 + r (latent_frames - 1)``."""
    return 1 + int(temporal_compression) * (int(latent_frames) - 1)


def temporal_compression_of(num_frames: int, num_latent_frames: int, default: int | None = 4) -> int | None:
    """The VAE's temporal ratio read off one clip: ``(num_frames - 1) / (num_latent_frames - 1)``; a one-frame
    clip states none (``default``). Refuses a pair no causal VAE makes (e.g. 49 frames, 12 latents)."""
    n, t = int(num_frames), int(num_latent_frames)
    if t <= 1 or n <= 1:
        return default
    if (n - 1) % (t - 1):
        raise ValueError(f"{n} pixel frames and {t} latent frames: no causal VAE ratio maps one onto the other")
    return (n - 1) // (t - 1)


@dataclass(frozen=True)
class ClipSpec:
    """Clip geometry. Defaults follow ReSim (10 Hz, 9 + 40 frames, 8 waypoints at 2 Hz)."""

    fps_hz: float = 10.0
    num_history_frames: int = 9
    num_future_frames: int = 40
    num_waypoints: int = 8
    waypoint_dt_s: float = 0.5
    vae_temporal_compression: int = 4

    def __post_init__(self):
        if self.fps_hz <= 0:
            raise ConfigError(f"fps_hz must be > 0, got {self.fps_hz}")
        if self.num_history_frames < 1 or self.num_future_frames < 1:
            raise ConfigError("num_history_frames and num_future_frames must be >= 1")
        if (self.num_frames - 1) % self.vae_temporal_compression:
            raise ConfigError(
                f"num_frames - 1 = {self.num_frames - 1} must be divisible by the VAE's temporal "
                f"compression {self.vae_temporal_compression} (CogVideoX's causal VAE keeps frame 0 alone)"
            )

    @property
    def num_frames(self) -> int:
        return self.num_history_frames + self.num_future_frames

    @property
    def num_latent_frames(self) -> int:
        return latent_frame_count(self.num_frames, self.vae_temporal_compression)

    @property
    def window_s(self) -> float:
        """Length of the future window in seconds (4 s by default)."""
        return self.num_future_frames / self.fps_hz


@dataclass(frozen=True)
class Member:
    """One tar member of a sample."""

    ext: str            # WebDataset extension (member name is KEY.EXT)
    encoding: str       # how the bytes are encoded: json | npy | mp4
    dtype: str | None   # numpy dtype after decoding (None for json/mp4)
    shape: str          # symbolic shape after decoding
    units: str
    optional: bool
    description: str


MEMBERS: dict[str, Member] = {
    m.ext: m
    for m in [
        Member("meta.json", "json", None, "object", "-", False,
               "Clip metadata, the keys in META_FIELDS."),
        Member("latent.npy", "npy", "float16|bfloat16", "(T_latent, C, h, w)",
               "VAE latent sample x scaling factor", False,
               "CogVideoX VAE latent of the clip's frames, one sample of the posterior (not the mean) "
               "times meta.latent_scaling_factor. bfloat16 is stored as its uint16 bit pattern "
               "(npy has no bf16); meta.latent_dtype says which."),
        Member("traj.npy", "npy", "float32", "(num_waypoints, 3)", "x m (forward), y m (left), yaw rad (left +)",
               True,
               "Future ego trajectory in the ego frame at the last history frame, at waypoint_dt_s steps "
               "(0.5 s ... 4.0 s). Present when the source has poses."),
        Member("frames.mp4", "mp4", "uint8", "(T, H_px, W_px, 3) RGB", "pixels 0..255", False,
               "Low-resolution pixel frames of the whole clip (history + future) at fps_hz, "
               "for the reward model, metrics against ground truth and previews."),
        Member("dino.npy", "npy", "float16", "(T_dino, N_tokens, D)", "DINOv2 last hidden state", True,
               "Precomputed per-frame DINOv2 features for Video2Reward (meta.dino_id names the backbone)."),
    ]
}


# members every sample has: a reader of whole samples treats a sample without one as bad
REQUIRED_MEMBERS: tuple[str, ...] = tuple(e for e, m in MEMBERS.items() if not m.optional)


@dataclass(frozen=True)
class MetaField:
    name: str
    type: str          # JSON type: str | int | float | bool | list | object, '|null' if nullable
    units: str
    description: str
    since: int = 1     # the schema version that added it (older samples lack it)


META_FIELDS: list[MetaField] = [
    MetaField("schema_version", "int", "-", "SCHEMA_VERSION of the writer."),
    MetaField("key", "str", "-", "The sample's __key__ (see make_key)."),
    MetaField("source", "str", "-", f"Source kind, one of {SOURCES}."),
    MetaField("item_id", "str", "-", "Source item (video / log / route) the clip was cut from; the episode id "
              "for splits (never split overlapping clips of one item across train/held-out)."),
    MetaField("start_frame", "int", "frames at fps_hz", "Index of the clip's first frame in the item, after resampling."),
    MetaField("start_s", "float", "s", "Clip start time within the item (after any start discard)."),
    MetaField("fps_hz", "float", "Hz", "Frame rate of the clip."),
    MetaField("num_frames", "int", "frames", "Frames in the clip (history + future)."),
    MetaField("num_history_frames", "int", "frames", "Conditioning frames at the start of the clip."),
    MetaField("num_future_frames", "int", "frames", "Frames to predict."),
    MetaField("height_px", "int", "px", "Height of the frames fed to the VAE."),
    MetaField("width_px", "int", "px", "Width of the frames fed to the VAE."),
    MetaField("frames_height_px", "int", "px", "Height of frames.mp4."),
    MetaField("frames_width_px", "int", "px", "Width of frames.mp4."),
    MetaField("command", "str", "-", f"The clip's driving command, one of {COMMANDS}."),
    MetaField("command_source", "str", "-", f"Where `command` came from: {COMMAND_SOURCES} "
              "(trajectory when the source has poses, else optical flow)."),
    MetaField("command_flow", "str|null", "-", "Command from optical flow (null if not computed)."),
    MetaField("command_trajectory", "str|null", "-", "Command from the trajectory (null without poses)."),
    MetaField("commands_agree", "bool|null", "-", "command_flow == command_trajectory where both exist."),
    MetaField("yaw_deg", "float", "deg, left +", "Heading change over the future window behind `command`."),
    MetaField("yaw_deg_flow", "float|null", "deg, left +", "Heading change estimated from optical flow."),
    MetaField("yaw_deg_trajectory", "float|null", "deg, left +", "Heading change from poses."),
    MetaField("confidence", "float", "0..1", "Confidence of `command`."),
    MetaField("is_turning", "bool", "-", "command != 'Moving forward' (and the car moves: never for a stopped clip)."),
    MetaField("balance_weight", "float", "-", "Sampling density the clip was extracted at relative to straight "
              "driving (e.g. 5.0 for turning windows with ReSim's 5x balance)."),
    MetaField("hazard", "bool|null", "-", "Hazardous (non-expert) episode; null for sources without outcomes."),
    MetaField("infraction_score", "float|null", "0..1", "Episode infraction score (1 = clean); null without outcomes."),
    MetaField("infractions", "list|null", "-", "Infraction names of the episode; null without outcomes."),
    MetaField("prompt_id", "str", "sha256 hex", "Prompt table id of the clip's text condition (prefix + command)."),
    MetaField("null_prompt_id", "str", "sha256 hex", "Prompt table id of the prefix alone (command dropped, for CFG)."),
    MetaField("vae_id", "str", "-", "Which VAE encoded the latent: its folder name, or 'PARENT/vae' for the vae/ "
              "folder of a diffusers pipeline (e.g. 'CogVideoX-2b/vae'); the default placeholder VAE writes "
              "'placeholder-cogvideox-vae-tiny'."),
    MetaField("vae_placeholder", "bool", "-", "True when the VAE is a random-init placeholder, not trained weights."),
    MetaField("latent_dtype", "str", "-", "float16 or bfloat16 (bfloat16 stored as uint16 bits)."),
    MetaField("latent_shape", "list", "-", "[T_latent, C, h, w]."),
    MetaField("latent_scaling_factor", "float", "-", "The VAE's scaling factor the latent was multiplied by."),
    MetaField("has_trajectory", "bool", "-", "Whether traj.npy is present."),
    MetaField("dino_id", "str|null", "-", "Backbone that produced dino.npy, when present."),
    MetaField("pipeline_version", "str", "-", "resim version that wrote the sample."),
    MetaField("config_hash", "str", "-", "resim.config.config_hash of the resolved pipeline config."),
    MetaField("ego_motion_pct_s", "float|null", "% of frame width / s",
              "Ego motion over the clip: median flow of its textured points (labeler), null where too little "
              "texture to tell.", since=2),
    MetaField("stopped", "bool|null", "-", "The car stands still (ego_motion_pct_s below labels.still's "
              "threshold); null where unknown or not tagged (labels.still.policy).", since=2),
    MetaField("signature", "str|null", "hex", "Perceptual signature for near-duplicate search: the 64-bit "
              "difference hash of 4 frames evenly spaced over the clip, 64 hex digits (resim/pipeline/dedup.py).",
              since=2),
    # per-clip quality (resim/pipeline/clip_quality.py), measured on the frames fed to the VAE (height_px x width_px)
    MetaField("luma_mean_8bit", "float|null", "0..255", "Brightness: mean luma (BT.601) over the clip.", since=3),
    MetaField("luma_std_8bit", "float|null", "0..127.5", "Contrast: spatial standard deviation of luma, mean over "
              "frames.", since=3),
    MetaField("sharpness_lapvar", "float|null", "8-bit levels^2", "Sharpness (low: blur): variance of the 3x3 "
              "Laplacian of luma, mean over frames; depends on the resolution.", since=3),
    MetaField("static_edge_frac", "float|null", "0..1", "Share of the frame covered by edges that do not move "
              "over the clip: dashboard, bonnet, burnt-in overlays (all of a stopped clip's edges).", since=3),
    MetaField("flow_quality", "float|null", "0..1", "Optical-flow quality over the clip: the labeler's share of "
              "points its rotation fit kept, / 0.25, capped at 1; null without flow.", since=3),
]
META_FIELD_NAMES = tuple(f.name for f in META_FIELDS)
QUALITY_META = ("luma_mean_8bit", "luma_std_8bit", "sharpness_lapvar", "static_edge_frac", "flow_quality")

# One manifest row per sample (Parquet), for stats and mixing weights without opening tars.
MANIFEST_COLUMNS = (
    "key", "shard", "source", "item_id", "start_frame", "command", "command_source", "is_turning",
    "hazard", "infraction_score", "has_trajectory", "prompt_id", "bytes_total", "ego_motion_pct_s", "stopped",
    "signature", *QUALITY_META,
)
# manifest columns copied from meta fields added after v1: absent from older manifests, read as null
MANIFEST_COLUMNS_SINCE = {f.name: f.since for f in META_FIELDS if f.since > 1 and f.name in MANIFEST_COLUMNS}


def meta_fields_of(version: int) -> list[MetaField]:
    """The meta fields a sample of schema ``version`` carries."""
    return [f for f in META_FIELDS if f.since <= version]


_KEY_SAFE = re.compile(r"[^A-Za-z0-9-]+")


def make_key(source: str, item_id: str, start_frame: int) -> str:
    """Deterministic sample key from (source kind, source item id, clip start frame).

    Readable prefix + an 10-hex hash of the full item id (so two ids that sanitise
    alike still differ). Only ``[A-Za-z0-9_-]``: WebDataset splits keys at the first
    dot, so a key must never contain one.
    """
    if source not in SOURCES:
        raise ValueError(f"unknown source kind {source!r}; expected one of {SOURCES}")
    if start_frame < 0:
        raise ValueError(f"start_frame must be >= 0, got {start_frame}")
    readable = _KEY_SAFE.sub("-", item_id).strip("-")[-40:] or "item"
    digest = hashlib.sha256(f"{source}\0{item_id}".encode()).hexdigest()[:10]
    return f"{source}_{readable}_{digest}_f{start_frame:07d}"


def prompt_id(text: str) -> str:
    """Prompt table id: sha256 of the exact prompt text."""
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def prompt_text(command: str | None) -> str:
    """ReSim's prompt: the fixed prefix joined with the command; the prefix alone for None (CFG null)."""
    if command is None:
        return PROMPT_PREFIX
    if command not in COMMANDS:
        raise ValueError(f"unknown command {command!r}; expected one of {COMMANDS}")
    return f"{PROMPT_PREFIX} {command}."


def schema_dict() -> dict[str, Any]:
    """The whole schema as plain data (for docs and `resim shards schema`)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "members": {k: dataclasses.asdict(m) for k, m in MEMBERS.items()},
        "meta_fields": [dataclasses.asdict(f) for f in META_FIELDS],
        "manifest_columns": list(MANIFEST_COLUMNS),
        "forbidden_extensions": list(FORBIDDEN_EXTENSIONS),
    }
