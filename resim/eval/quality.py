"""Streaming video-quality evaluation of (generated, ground truth) clip pairs.

``VideoQualityEvaluator(cfg).update(generated, ground_truth)`` takes batches of clips ``(B, T, C, H, W)`` in
the range ``cfg.value_range`` states (``"uint8"``: integers 0..255, ``"unit"``: floats in [0, 1]; never
guessed). The first ``cfg.num_conditioning_frames`` frames of every clip are the frames the model was given
(ReSim: 9 history frames) and are excluded from every metric; the remaining *future* frames are scored:

* PSNR, SSIM, LPIPS (and DreamSim when available) per frame, accumulated per future-frame index, and
  grouped by **prediction horizon**: bin ``i`` holds the frames whose time after the last conditioning
  frame, ``(k + 1) / fps_hz`` for future frame ``k``, lies in ``(h_{i-1}, h_i]`` (default horizons 1, 2, 4,
  8, ... s up to the clip length);
* FID of generated future frames against ground-truth future frames (Inception-v3 pool3, eval mode), per
  horizon bin and over all future frames;
* FVD of whole future clips (I3D), and of the first ``h`` seconds of them for each horizon ``h`` with at least
  ``MIN_FVD_FRAMES`` frames.

Only sums are kept (per-frame metric sums, Gaussian feature sums), so any number of clips streams through.
``compute()`` returns a report dict whose ``protocol`` entry names everything a number depends on: sample
counts, resolution and resize method, frames used, network names with the sha256 of their weights
(``random-init`` for placeholders), device. See docs/eval.md.
"""
from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import pickle
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

import torch
import torch.nn.functional as F

from resim.config import ConfigError
from resim.eval.fidelity import PSNR_CAP_DB, psnr, ssim, to_unit
from resim.eval.frechet import MIN_SAMPLES_UNBIASED, FeatureStats, frechet_from_stats
from resim.eval.i3d import I3D
from resim.eval.inception import FIDInception
from resim.eval.lpips import LPIPS
from resim.media.device import resolve_device

MIN_FVD_FRAMES = 9          # I3D's first conv spans 7 frames at stride 2; FVD clips are conventionally >= 16
PER_FRAME_METRICS = ("psnr", "ssim", "lpips", "dreamsim")
ALL_METRICS = ("psnr", "ssim", "lpips", "fid", "fvd", "dreamsim")


@dataclass
class QualityConfig:
    """What to measure and how. Paths are local weight files; ``None`` builds a random-init placeholder
    network (allowed only with ``allow_placeholder_networks``: its numbers compare nothing with anything)."""

    value_range: Literal["uint8", "unit"] = "uint8"
    fps_hz: float = 10.0
    num_conditioning_frames: int = 9            # leading frames given to the model: excluded from all metrics
    horizons_s: tuple[float, ...] = ()          # () = 1, 2, 4, 8, ... s up to the clip length
    resolution_hw: tuple[int, int] = (0, 0)     # (0, 0): score at the input resolution; else resize both first
    metrics: tuple[str, ...] = ("psnr", "ssim", "lpips", "fid", "fvd", "dreamsim")
    lpips_net: Literal["vgg", "alex"] = "vgg"
    lpips_trunk_weights: Optional[Path] = None  # torchvision vgg16-397923af.pth / alexnet-owt-7be5be79.pth
    lpips_head_weights: Optional[Path] = None   # lpips weights/v0.1/{vgg,alex}.pth
    fid_weights: Optional[Path] = None          # pytorch-fid pt_inception-2015-12-05-6726825d.pth
    fvd_weights: Optional[Path] = None          # pytorch-i3d models/rgb_imagenet.pt
    fvd_feature_layer: Literal["logits", "pool"] = "logits"
    dreamsim_dir: Optional[Path] = None         # a dreamsim cache_dir with the checkpoint already extracted
    dreamsim_type: str = "ensemble"
    allow_placeholder_networks: bool = False
    feature_batch_size: int = 16                # frames per Inception/LPIPS call
    device: str = "auto"                        # auto: cuda if available, else cpu

    def __post_init__(self):
        if self.value_range not in ("uint8", "unit"):
            raise ConfigError(f"value_range must be 'uint8' or 'unit', got {self.value_range!r}")
        # math.isfinite: nan slips through `<= 0` tests (and would silently empty every horizon bin)
        if not (math.isfinite(self.fps_hz) and self.fps_hz > 0):
            raise ConfigError(f"fps_hz must be a finite number > 0, got {self.fps_hz}")
        if self.num_conditioning_frames < 0:
            raise ConfigError("num_conditioning_frames must be >= 0")
        if (any(not (math.isfinite(h) and h > 0) for h in self.horizons_s)
                or list(self.horizons_s) != sorted(set(self.horizons_s))):
            raise ConfigError(f"horizons_s must be increasing, finite and > 0, got {self.horizons_s}")
        bad = [m for m in self.metrics if m not in ALL_METRICS]
        if bad:
            raise ConfigError(f"unknown metrics {bad}; known: {ALL_METRICS}")
        if (self.resolution_hw[0] > 0) != (self.resolution_hw[1] > 0):
            raise ConfigError(f"resolution_hw must be (0, 0) or both > 0, got {self.resolution_hw}")
        if self.feature_batch_size < 1:
            raise ConfigError("feature_batch_size must be >= 1")


def horizon_bins(num_future_frames: int, fps_hz: float, horizons_s: tuple[float, ...] = ()) -> list[dict]:
    """Bins of future-frame indices by prediction horizon.

    Future frame ``k`` (0-based, after the last conditioning frame) is ``(k + 1) / fps_hz`` s ahead.
    Default horizons: 1, 2, 4, 8, ... s until the clip is covered. Returns ``[{"horizon_s", "from_s",
    "frames": [k...]}]`` for bins holding at least one frame.
    """
    if num_future_frames < 1:
        raise ValueError("no future frames to score (num_conditioning_frames >= clip length)")
    length_s = num_future_frames / fps_hz
    hs = list(horizons_s)
    if not hs:
        h = 1.0
        while True:
            hs.append(h)
            if h >= length_s - 1e-9:
                break
            h *= 2
    times = [(k + 1) / fps_hz for k in range(num_future_frames)]
    out, lo = [], 0.0
    for h in hs:
        ks = [k for k, t in enumerate(times) if lo + 1e-9 < t <= h + 1e-9]
        if ks:
            out.append({"horizon_s": float(h), "from_s": float(lo), "frames": ks})
        lo = h
    return out


@dataclass
class Networks:
    """The feature networks an evaluator uses (any module with the same call signature and a
    ``weights_sha256`` attribute can stand in, e.g. small networks in tests)."""

    fid: Any = None        # frames (N, 3, H, W) [0, 1] -> (N, D)
    fvd: Any = None        # clips (B, T, 3, H, W) [0, 1] -> (B, D)
    lpips: Any = None      # two (N, 3, H, W) [0, 1] -> (N,)
    dreamsim: Any = None   # two (N, 3, H, W) [0, 1] -> (N,)
    names: dict[str, str] = field(default_factory=dict)
    dreamsim_reason: str = ""


def dreamsim_status(cfg: QualityConfig) -> tuple[bool, str]:
    """(available, reason). Never downloads: needs the package and a local, already-extracted cache."""
    if "dreamsim" not in cfg.metrics:
        return False, "not requested"
    if importlib.util.find_spec("dreamsim") is None:
        return False, "the 'dreamsim' package is not installed (pip install dreamsim; see docs/eval.md)"
    if cfg.dreamsim_dir is None:
        return False, "no dreamsim_dir given (a local DreamSim cache with the extracted checkpoint; we never download)"
    d = Path(cfg.dreamsim_dir)
    if not d.is_dir():
        return False, f"dreamsim_dir {d} does not exist"
    if not any(p.is_dir() and "lora" in p.name for p in d.iterdir()):
        return False, f"dreamsim_dir {d} holds no extracted '*_lora' checkpoint folder (see docs/eval.md)"
    return True, ""


class _DreamSimAdapter:
    """DreamSim's model as ``(x, y) -> (N,)`` on [0, 1] frames (224x224 bicubic, as its preprocess does)."""

    def __init__(self, cfg: QualityConfig, device: str):
        os.environ.setdefault("HF_HUB_OFFLINE", "1")   # the backbones must come from the local cache
        # DreamSim is an optional package (with its own weights): only when the metric is asked for
        from dreamsim import dreamsim  # type: ignore[import-not-found]

        self.model, _ = dreamsim(pretrained=True, device=device, cache_dir=str(cfg.dreamsim_dir),
                                 dreamsim_type=cfg.dreamsim_type)
        self.weights_sha256 = _dir_sha256(Path(cfg.dreamsim_dir))

    @torch.no_grad()
    def __call__(self, x, y):
        x = F.interpolate(x.float(), size=(224, 224), mode="bicubic", align_corners=False).clamp(0, 1)
        y = F.interpolate(y.float(), size=(224, 224), mode="bicubic", align_corners=False).clamp(0, 1)
        return self.model(x, y).flatten()


def _dir_sha256(d: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(d.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(d).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def build_networks(cfg: QualityConfig, device: str) -> Networks:
    """Load the requested networks from local files; random-init placeholders only when allowed."""
    def need(name: str, **paths) -> bool:
        if name not in cfg.metrics:
            return False
        if any(p is None for p in paths.values()) and not cfg.allow_placeholder_networks:
            raise ConfigError(f"{name}: no weights file given and allow_placeholder_networks is off "
                              "(see docs/eval.md for where to get the standard weights)")
        for key, p in paths.items():  # a given file must exist: checked before any network is built
            if p is not None and not Path(p).is_file():
                raise ConfigError(f"{name}: {key} {p} is not a file (see docs/eval.md for the standard weights)")
        return True

    def load(name: str, fn):
        """A user's weight file that torch cannot read (truncated, not a state dict, wrong layout) is a
        ConfigError naming it; anything else is our bug and propagates."""
        try:
            return fn()
        except (RuntimeError, ValueError, pickle.UnpicklingError, EOFError) as e:
            raise ConfigError(f"{name}: cannot load its weights: {str(e).splitlines()[0][:300]}") from None

    nets = Networks()
    if need("fid", fid_weights=cfg.fid_weights):
        nets.fid = load("fid", lambda: FIDInception.from_file(cfg.fid_weights)) if cfg.fid_weights else FIDInception()
        nets.fid.to(device)
        nets.names["fid"] = "Inception-v3 pool3 2048-d (pytorch-fid FIDInceptionV3 layout)"
    if need("fvd", fvd_weights=cfg.fvd_weights):
        nets.fvd = (load("fvd", lambda: I3D.from_file(cfg.fvd_weights, cfg.fvd_feature_layer)) if cfg.fvd_weights
                    else I3D(cfg.fvd_feature_layer)).to(device)
        nets.names["fvd"] = f"I3D {cfg.fvd_feature_layer} (pytorch-i3d InceptionI3d layout)"
    if need("lpips", lpips_trunk_weights=cfg.lpips_trunk_weights, lpips_head_weights=cfg.lpips_head_weights):
        nets.lpips = (load("lpips", lambda: LPIPS.from_files(cfg.lpips_net, cfg.lpips_trunk_weights,
                                                             cfg.lpips_head_weights))
                      if cfg.lpips_trunk_weights and cfg.lpips_head_weights else LPIPS(cfg.lpips_net)).to(device)
        nets.names["lpips"] = f"LPIPS v0.1 {cfg.lpips_net}"
    ok, reason = dreamsim_status(cfg)
    if ok:
        nets.dreamsim = _DreamSimAdapter(cfg, device)
        nets.names["dreamsim"] = f"DreamSim {cfg.dreamsim_type}"
    nets.dreamsim_reason = reason
    return nets


class _FrameSums:
    """Per future-frame-index sums of one per-frame metric (streaming mean/std per frame and per bin).

    ``cap``: the metric's cap (PSNR: ``PSNR_CAP_DB`` for identical frames); values at the cap are counted per
    frame index, so every mean that includes them is reported with how many (``capped_frames``)."""

    def __init__(self, t: int, cap: float | None = None):
        self.s = torch.zeros(t, dtype=torch.float64)
        self.s2 = torch.zeros(t, dtype=torch.float64)
        self.n = torch.zeros(t, dtype=torch.float64)
        self.cap = cap
        self.capped = torch.zeros(t, dtype=torch.int64)   # (T,) frames that scored the cap, per frame index

    def add(self, v: torch.Tensor) -> None:  # (B, T)
        v = v.detach().to("cpu", torch.float64)
        self.s += v.sum(0)
        self.s2 += (v * v).sum(0)
        self.n += v.shape[0]
        if self.cap is not None:
            self.capped += (v >= self.cap).sum(0)

    def summary(self, ks) -> dict:
        ks = torch.as_tensor(list(ks))
        n = float(self.n[ks].sum())
        out: dict[str, Any] = {"mean": None, "std": None, "frames": int(n)}
        if n:
            m = float(self.s[ks].sum()) / n
            var = max(float(self.s2[ks].sum()) / n - m * m, 0.0)
            out.update(mean=m, std=math.sqrt(var))
        if self.cap is not None:
            out.update(capped_frames=int(self.capped[ks].sum()), cap=self.cap)
        return out


class VideoQualityEvaluator:
    """Streaming PSNR/SSIM/LPIPS/DreamSim per frame and horizon, FID per horizon, FVD per clip horizon."""

    def __init__(self, cfg: QualityConfig, networks: Networks | None = None):
        self.cfg = cfg
        self.device = resolve_device(cfg.device)
        self.nets = networks if networks is not None else build_networks(cfg, self.device)
        self._dreamsim_reason = self.nets.dreamsim_reason or ("" if self.nets.dreamsim is not None
                                                              else "no DreamSim network given")
        self.t_future: int | None = None      # fixed by the first accepted batch (see _geometry)
        self.input_hw: tuple[int, int] | None = None
        self.bins: list[dict] = []
        self.sums: dict[str, _FrameSums] = {}
        self.fid_stats: list | None = None
        self.fid_all: tuple = (None, None)
        self.fvd_windows: list[dict] = []
        self.fvd_skipped: list[str] = []
        self.clips = 0

    # ---------------------------------------------------------------------------------------------- set-up
    def _geometry(self, t: int, hw: tuple[int, int]) -> dict:
        """The per-geometry state (bins, sums, FVD windows) for clips of ``t`` frames at ``hw``, built without
        touching ``self``: :meth:`update` commits it only once its first batch has been scored in full."""
        c = self.cfg
        tf = t - c.num_conditioning_frames
        bins = horizon_bins(tf, c.fps_hz, tuple(c.horizons_s))   # ValueError when no future frame is left
        st: dict[str, Any] = {"t_future": tf, "input_hw": hw, "bins": bins,
                              "sums": {m: _FrameSums(tf, PSNR_CAP_DB if m == "psnr" else None)
                                       for m in PER_FRAME_METRICS if self._on(m)},
                              "fid_stats": None, "fid_all": (None, None), "fvd_windows": [], "fvd_skipped": []}
        if self._on("fid"):
            st["fid_stats"] = [(None, None) for _ in bins]  # created lazily (feature dim from the network)
        if self._on("fvd"):
            for b in bins:
                n = int(round(b["horizon_s"] * c.fps_hz))
                n = min(n, tf)
                if n >= MIN_FVD_FRAMES and all(w["frames"] != n for w in st["fvd_windows"]):
                    st["fvd_windows"].append({"horizon_s": min(b["horizon_s"], tf / c.fps_hz), "frames": n,
                                              "stats": (None, None)})
            st["fvd_skipped"] = [] if st["fvd_windows"] else [
                f"the future has {tf} frames; FVD needs >= {MIN_FVD_FRAMES}"]
        return st

    def _on(self, metric: str) -> bool:
        if metric not in self.cfg.metrics:
            return False
        net = {"fid": self.nets.fid, "fvd": self.nets.fvd, "lpips": self.nets.lpips,
               "dreamsim": self.nets.dreamsim}.get(metric, True)
        return net is not None

    def _prepare(self, video: torch.Tensor) -> torch.Tensor:
        """Stated range → float64 [0, 1] future frames at the metric resolution, on the device (PSNR/SSIM
        run in float64; the networks get float32)."""
        x = to_unit(video, self.cfg.value_range)[:, self.cfg.num_conditioning_frames:]
        rh, rw = self.cfg.resolution_hw
        if rh and (rh, rw) != tuple(x.shape[-2:]):
            b, t = x.shape[:2]
            x = F.interpolate(x.flatten(0, 1), size=(rh, rw), mode="bilinear", align_corners=False, antialias=True)
            x = x.clamp(0, 1).view(b, t, *x.shape[1:])
        return x.to(self.device)

    # ---------------------------------------------------------------------------------------------- update
    @torch.no_grad()
    def update(self, generated: torch.Tensor, ground_truth: torch.Tensor) -> None:
        """Add a batch of clip pairs, each ``(B, T, C, H, W)`` in ``cfg.value_range`` (C = 3).

        A batch is scored in full before anything is kept: a rejected batch (wrong dtype/range, too few frames,
        frames too small for SSIM, ...) leaves the evaluator as it was, and in particular does not fix the
        clip geometry for the batches after it."""
        if generated.shape != ground_truth.shape:
            raise ValueError(f"generated {tuple(generated.shape)} and ground truth {tuple(ground_truth.shape)} "
                             "differ in shape (resize before, or set resolution_hw)")
        if generated.ndim != 5 or generated.shape[2] != 3:
            raise ValueError(f"expected RGB clips (B, T, 3, H, W), got {tuple(generated.shape)}")
        t, hw = generated.shape[1], tuple(generated.shape[-2:])
        if self.t_future is not None and (t - self.cfg.num_conditioning_frames != self.t_future
                                          or hw != self.input_hw):
            raise ValueError(f"clips of {t} frames at {hw} after clips of "
                             f"{self.t_future + self.cfg.num_conditioning_frames} frames at {self.input_hw}: "
                             "one evaluator per clip geometry")
        g, r = self._prepare(generated), self._prepare(ground_truth)   # value-range checks
        st = self._geometry(t, hw) if self.t_future is None else None
        bins = st["bins"] if st is not None else self.bins
        sums = st["sums"] if st is not None else self.sums
        fvd_windows = st["fvd_windows"] if st is not None else self.fvd_windows
        b, tf = g.shape[:2]
        # score everything first (any of these may reject the batch) ...
        per_frame: dict[str, torch.Tensor] = {}
        if "psnr" in sums:
            per_frame["psnr"] = psnr(g, r, "unit")
        if "ssim" in sums:
            per_frame["ssim"] = ssim(g, r, "unit")
        g, r = g.float(), r.float()
        for name in ("lpips", "dreamsim"):
            if name in sums:
                per_frame[name] = self._pairwise(getattr(self.nets, name), g, r).view(b, tf)
        fid = None
        if self._on("fid"):
            fid = (self._features(g.flatten(0, 1)).view(b, tf, -1), self._features(r.flatten(0, 1)).view(b, tf, -1))
        fvd = [(self.nets.fvd(g[:, :w["frames"]]), self.nets.fvd(r[:, :w["frames"]])) for w in fvd_windows]
        # ... then keep it
        if st is not None:
            self.t_future, self.input_hw, self.bins, self.sums = st["t_future"], st["input_hw"], bins, sums
            self.fid_stats, self.fid_all = st["fid_stats"], st["fid_all"]
            self.fvd_windows, self.fvd_skipped = fvd_windows, st["fvd_skipped"]
        for name, v in per_frame.items():
            self.sums[name].add(v)
        if fid is not None:
            self._update_fid(*fid)
        for w, (fg, fr) in zip(self.fvd_windows, fvd):
            w["stats"] = self._acc(w["stats"], fg, fr)
        self.clips += b

    def _pairwise(self, net, g, r) -> torch.Tensor:
        x, y = g.flatten(0, 1), r.flatten(0, 1)
        bs = self.cfg.feature_batch_size
        return torch.cat([net(x[i:i + bs], y[i:i + bs]).flatten().float().cpu() for i in range(0, len(x), bs)])

    def _features(self, frames: torch.Tensor) -> torch.Tensor:
        bs = self.cfg.feature_batch_size
        return torch.cat([self.nets.fid(frames[i:i + bs]).float().cpu() for i in range(0, len(frames), bs)])

    @staticmethod
    def _acc(pair, fg, fr):
        sg, sr = pair
        if sg is None:
            sg, sr = FeatureStats(fg.shape[1]), FeatureStats(fr.shape[1])
        sg.update(fg)
        sr.update(fr)
        return sg, sr

    def _update_fid(self, fg, fr) -> None:
        """Accumulate frame features ``(B, T_future, D)`` of generated / ground-truth clips."""
        for i, bin_ in enumerate(self.bins):
            ks = bin_["frames"]
            self.fid_stats[i] = self._acc(self.fid_stats[i], fg[:, ks].flatten(0, 1), fr[:, ks].flatten(0, 1))
        self.fid_all = self._acc(self.fid_all, fg.flatten(0, 1), fr.flatten(0, 1))

    # ---------------------------------------------------------------------------------------------- report
    def protocol(self) -> dict:
        c = self.cfg
        rh, rw = c.resolution_hw
        nets = {}
        for name in ("fid", "fvd", "lpips", "dreamsim"):
            net = getattr(self.nets, name)
            if net is not None and name in c.metrics:
                nets[name] = {"network": self.nets.names.get(name, type(net).__name__),
                              "weights_sha256": getattr(net, "weights_sha256", "unknown")}
        placeholders = sorted(k for k, v in nets.items() if v["weights_sha256"] == "random-init")
        return {
            "clips": self.clips,
            "clip_frames": None if self.t_future is None else self.t_future + c.num_conditioning_frames,
            "conditioning_frames_excluded": c.num_conditioning_frames,
            "future_frames_scored": self.t_future,
            "fps_hz": c.fps_hz,
            "value_range": c.value_range,
            "input_resolution_hw": list(self.input_hw) if self.input_hw else None,
            "metric_resolution_hw": [rh, rw] if rh else (list(self.input_hw) if self.input_hw else None),
            "resize": (f"bilinear, antialias, align_corners=False to {rh}x{rw} (both sets)" if rh else "none"),
            "horizon_bins_s": [[b["from_s"], b["horizon_s"]] for b in self.bins],
            "psnr": f"10 log10(1/MSE) on [0,1] RGB per frame, capped at {PSNR_CAP_DB} dB (identical frames); "
                    "means include capped frames, counted in capped_frames",
            "ssim": "Gaussian 11x11 sigma 1.5, K=(0.01,0.03), valid region, channel mean (= scikit-image)",
            "fid": "generated future frames vs ground-truth future frames; Inception input 299x299 bilinear "
                   "(align_corners=False), [-1,1], eval mode",
            "fvd": "I3D on the first h s of the future (whole clips per horizon); input 224x224 bilinear, [-1,1]",
            "networks": nets,
            "placeholder_networks": placeholders,
            "dreamsim": {"available": self.nets.dreamsim is not None and "dreamsim" in c.metrics,
                         "reason": self._dreamsim_reason},
            "min_samples_unbiased": MIN_SAMPLES_UNBIASED,
            "device": self.device,
            "torch": torch.__version__,
        }

    def compute(self) -> dict:
        """The report: ``{"protocol", "overall", "per_horizon", "per_frame", "warnings"}``."""
        if self.clips == 0:   # an empty report would read as a result; say why there is none
            raise ValueError("no clips were added (every update() was rejected, or none was called): "
                             "nothing to report")
        warns: list[str] = []
        overall: dict[str, Any] = {}
        all_k = range(self.t_future)
        for m, s in self.sums.items():
            overall[m] = s.summary(all_k)
        if "psnr" in self.sums:   # the PSNR means include frames at the cap: say how many
            o = overall["psnr"]
            o["cap_db"] = o.pop("cap")
            if o["capped_frames"]:
                warns.append(f"PSNR: {o['capped_frames']} of {o['frames']} future frames are identical to the ground "
                             f"truth and score the cap {PSNR_CAP_DB:g} dB; the PSNR means include them "
                             "(capped_frames per horizon and per frame)")
        per_h = []
        for i, b in enumerate(self.bins):
            row: dict[str, Any] = {"horizon_s": b["horizon_s"], "from_s": b["from_s"],
                                   "frames_per_clip": len(b["frames"])}
            for m, s in self.sums.items():
                row[m] = s.summary(b["frames"])["mean"]
            if "psnr" in self.sums:
                row["psnr_capped_frames"] = self.sums["psnr"].summary(b["frames"])["capped_frames"]
            if self.fid_stats is not None:
                row["fid"] = self._frechet(self.fid_stats[i], f"FID ({b['from_s']:g}-{b['horizon_s']:g} s)", warns)
            per_h.append(row)
        if self.fid_stats is not None:
            overall["fid"] = self._frechet(self.fid_all, "FID (all future frames)", warns)
        fvd_rows = []
        for w in self.fvd_windows:
            fvd_rows.append({"horizon_s": w["horizon_s"], "frames": w["frames"],
                             "fvd": self._frechet(w["stats"], f"FVD (first {w['frames']} future frames)", warns)})
        if fvd_rows:
            overall["fvd"] = fvd_rows[-1]["fvd"]
            overall["fvd_frames"] = fvd_rows[-1]["frames"]
        elif "fvd" in self.cfg.metrics:
            overall["fvd"] = None
            warns.extend(self.fvd_skipped or ["FVD: no network"])
        per_frame = {"time_s": [(k + 1) / self.cfg.fps_hz for k in all_k]}
        for m, s in self.sums.items():
            per_frame[m] = (s.s / s.n.clamp_min(1)).tolist()
        if "psnr" in self.sums:
            per_frame["psnr_capped_frames"] = self.sums["psnr"].capped.tolist()
        proto = self.protocol()
        if proto["placeholder_networks"]:
            warns.append(f"placeholder (random-init) networks for {proto['placeholder_networks']}: these numbers "
                         "test the plumbing only and are comparable with nothing")
        if not proto["dreamsim"]["available"] and "dreamsim" in self.cfg.metrics:
            overall["dreamsim"] = f"not available: {proto['dreamsim']['reason']}"
        return {"protocol": proto, "overall": overall, "per_horizon": per_h, "fvd_per_horizon": fvd_rows,
                "per_frame": per_frame, "warnings": warns}

    @staticmethod
    def _frechet(pair, name: str, warns: list[str]) -> float | None:
        sg, sr = pair
        if sg is None or sg.n < 2:
            warns.append(f"{name}: fewer than 2 samples, not computed")
            return None
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = frechet_from_stats(sg, sr, name)
        for w in caught:
            warns.append(str(w.message))
            warnings.warn(str(w.message), stacklevel=3)
        return res.value
