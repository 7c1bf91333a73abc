"""How far did a generated future drive? Read it off the synthetic world itself, not off an IDM.

    python lab/render_match.py --world runs/v6/world1008 --shards runs/v6/ctl1008 --limit 24 \
        --given-scales 0.5,1.0,1.5 --idm synth-idm --idm runs/v5/idm77d --out runs/v6/rm1008   # ~10 min, 2 cores

Trajectory Difference reads the path a rollout drove with an inverse dynamics model (IDM). IDMs that agree
within 1 m on every real video (recorded or decoded through the VAE) disagree by 14 m on rollouts
(docs/lab/2026-11-26-synth-world-stage-chain.md), and nothing said which was right: a check needs generated video
whose motion is known. In the synthetic world the scene is known exactly, so the motion of any video of it can
be read by re-rendering. For each clip (a CARLA-layout episode of a ``resim synth`` world, which this script rebuilds
from its seed) the future is rendered along the recorded path with the distance driven scaled by ``k``
(``k = 0``: standing still; ``1``: the recorded drive; ``2``: twice as far), each candidate is encoded by the
VAE that encoded the shards, and a rollout's future latents are matched to the candidates. The ``k`` with the
least squared error over the future (refined by a parabola through its neighbours) gives the distance driven.

The world model is given the recorded trajectory with its distance scaled by each ``--given-scales`` value (the
same path, other speeds), so the reading can be compared with what it was given clip by clip: the within-clip
slope of the distance read on the distance given (1: followed; 0: ignored), where a reader's constant bias cancels.
It reads speed along the recorded path only: a rollout that leaves that path (an explorer's, whose recorded path
leaves the road) is outside what the renders describe; ``contrast`` (worst / best MSE) says how well the best fits.

Known answers the reader must read: the recorded latents themselves (k = 1 by construction: this checks that the
world is rebuilt exactly), and the recorded latents decoded and encoded again by the VAE (the smoothing a rollout
goes through; no candidate is exact any more).

Per clip and scale: the distance read this way at 4 s, the given one, and each ``--idm``'s reading of the same
decoded rollout and of the recorded video. Each IDM's own known answer: the clip re-rendered at each given scale (a
true video of the same path at another speed), raw and through the VAE, read against the render's distance; an IDM
that has learnt the speed an expert drives on such a road instead of reading the motion fails it.
Writes OUT/render_match.json and OUT/render_match.png.

A probe script, not a product command: it imports the synthetic world's generator (``pipelines``), which
``training`` must not.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from resim.config import from_dict
from resim.diffusion.guidance import guidance_preset
from resim.eval.worldeval import WorldRollouts, _idm_on, eval_clips_from_dataset
from resim.labeling.trajectory import trajectory_from_poses
from resim.media.encoders import VideoVAE
from resim.media.frames import cover_crop
from resim.pipeline.sources.synth.generate import SynthConfig, episode_renderer, plan_episodes
from resim.pipeline.stages.encode import key_seed
from resim.sample.load import PromptSource, encoded_with, load_world_model, run_objective
from resim.sample.rollout import ROLLOUT_PRESETS, RolloutConfig
from resim.shards.reader import iter_samples
from resim.train.tasks.idm import load_idm

REPO = Path(__file__).resolve().parents[1]

K_GRID = np.round(np.arange(0.0, 2.41, 0.1), 2)      # distance scale of the candidate futures
# latent rows (of 8 at 64 px): the horizon is at 0.42 of the height (resim.synthworld.render.Camera), latent row ~3.4
REGIONS = {"upper": slice(0, 4), "lower": slice(4, None)}


def log(msg: str) -> None:
    print(f"[render_match] {time.strftime('%H:%M:%S')} {msg}", file=sys.stderr, flush=True)


class WorldRebuild:
    """The episodes of a ``resim synth`` world, rebuilt from its seed: world, renderer, 20-Hz poses."""

    def __init__(self, root: Path):
        cfg_d = json.loads((root / "synth_config.json").read_text())
        self.seed, n = int(cfg_d.pop("seed")), int(cfg_d.pop("episodes"))
        self.cfg = from_dict(SynthConfig, cfg_d)
        gt = json.loads((root / "ground_truth.json").read_text())
        self.by_item = {e["layout"]["item_id"]: e for e in gt["episodes"]}
        self.plans = plan_episodes(n, self.cfg)
        self._cache: dict = {}

    def episode(self, item_id: str):
        if item_id not in self._cache:
            e = self.by_item[item_id]
            renderer, tr = episode_renderer(self.plans[e["index"]], self.seed, self.cfg)
            if not np.allclose(tr.poses[:, 0], e["x_m"]) or not np.allclose(tr.poses[:, 1], e["y_m"]):
                raise RuntimeError(f"{item_id}: the rebuilt drive differs from ground_truth.json")
            self._cache = {item_id: (renderer, tr)}   # one at a time: maps are large
        return self._cache[item_id]


def path_poses(poses: np.ndarray, t_s: np.ndarray, t0_s: float, times_s: np.ndarray, k: float) -> np.ndarray:
    """Poses (len(times_s), 3) along the recorded path, where the distance driven since ``t0_s`` is ``k`` times the
    recorded one at each time. Past the episode's end the path goes on straight."""
    seg = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    yaw = np.unwrap(poses[:, 2])
    s0 = np.interp(t0_s, t_s, s)
    target = s0 + k * (np.interp(times_s, t_s, s) - s0)
    out = np.stack([np.interp(target, s, poses[:, 0]), np.interp(target, s, poses[:, 1]),
                    np.interp(target, s, yaw)], axis=1)
    over = target > s[-1]
    if over.any():
        d = target[over] - s[-1]
        out[over, 0] = poses[-1, 0] + d * np.cos(yaw[-1])
        out[over, 1] = poses[-1, 1] + d * np.sin(yaw[-1])
        out[over, 2] = yaw[-1]
    return out


def candidates(wr: WorldRebuild, clip, start_s: float, vae: VideoVAE,
               hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, list]:
    """Latents ``(len(K_GRID), T_lat, C, h, w)`` of the clip's future rendered at each distance scale, the
    end point (x, y) at 4 s of each candidate, in the ego frame of the last history frame, and the rendered videos
    (``len(K_GRID)`` of ``(T, H, W, 3)`` uint8). ``start_s``: the clip's first frame in the episode (its
    ``meta.json``)."""
    renderer, tr = wr.episode(clip.item_id)
    t_s = np.asarray(tr.t_s)
    n = clip.frames.shape[0]
    times = start_s + np.arange(n) / clip.fps_hz
    t_hist = times[clip.num_history_frames - 1]
    videos, ends = [], []
    for k in K_GRID:
        poses = path_poses(tr.poses, t_s, t_hist, times, float(k))
        frames = [jpeg(cover_crop(renderer.render(p, t), hw), wr.cfg.jpeg_quality) for p, t in zip(poses, times)]
        videos.append(np.stack(frames))
        ends.append(trajectory_from_poses(poses, clip.num_history_frames - 1, clip.fps_hz)[-1, :2])
    seeds = [key_seed(clip.key)] * len(videos)
    lat = np.concatenate([vae.encode(np.stack(videos[i:i + 5]), seeds[i:i + 5]) for i in range(0, len(videos), 5)])
    return lat, np.stack(ends), videos


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """The CARLA layout stores JPEGs: the round trip the clips the shards were made from went through. (Here after
    the resize, where the pipeline resized the decoded JPEG: a small difference; the recorded latents still read
    k = 1.00 with a contrast of ~800.)"""
    ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]


def read_scale(future: np.ndarray, cand: np.ndarray, h_lat: int,
               rows: slice = slice(None)) -> tuple[float, float, np.ndarray]:
    """The distance scale ``k`` whose candidate matches ``future`` best over the whole future (least squared error
    summed over the future latent frames; parabolic refinement between grid points), the error curve's contrast
    (worst / best MSE: ~1 when no candidate fits better than another), and the best ``k`` per latent frame.
    ``future``: (T_lat, C, h, w); ``cand``: (K, T_lat, C, h, w); ``rows``: the latent rows compared (all by default).
    """
    mse = ((cand[:, h_lat:, :, rows] - future[None, h_lat:, :, rows]) ** 2).mean(axis=(2, 3, 4))      # (K, F)
    per_frame = np.array([_argmin_refined(mse[:, j]) for j in range(mse.shape[1])])
    m = mse.mean(axis=1)
    return _argmin_refined(m), float(m.max() / max(m.min(), 1e-12)), per_frame


def _argmin_refined(m: np.ndarray) -> float:
    i = int(np.argmin(m))
    k = float(K_GRID[i])
    if 0 < i < len(m) - 1:
        den = m[i - 1] - 2 * m[i] + m[i + 1]
        if den > 0:
            k += float(np.clip(0.5 * (m[i - 1] - m[i + 1]) / den, -0.5, 0.5)) * float(K_GRID[1] - K_GRID[0])
    return k


def scaled_trajectory(wr: WorldRebuild, clip, start_s: float, k: float) -> np.ndarray:
    """The clip's trajectory (8, 3) with the distance driven scaled by ``k`` along the recorded path (the shards'
    ``traj.npy`` at ``k = 1``: ``resim.labeling.trajectory`` on the path's poses every 0.5 s)."""
    _, tr = wr.episode(clip.item_id)
    t_hist = start_s + (clip.num_history_frames - 1) / clip.fps_hz
    p = path_poses(tr.poses, np.asarray(tr.t_s), t_hist, t_hist + np.arange(0, 9) * 0.5, k)
    return trajectory_from_poses(p, 0, fps_hz=2.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", required=True, help="the resim synth world the shards were made from")
    ap.add_argument("--shards", required=True, help="its CARLA-layout clips (resim pipeline run)")
    ap.add_argument("--checkpoint", default="synth-world")
    ap.add_argument("--idm", action="append", default=[], help="IDM run(s) to read the same videos (repeatable)")
    ap.add_argument("--limit", type=int, default=24)
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--seed", type=int, default=0, help="rollout seed (resim eval control's default: 0)")
    ap.add_argument("--given-scales", default="0.5,1.0,1.5",
                    help="the recorded trajectory's distance scaled by each of these is given to the world model")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scales = [float(x) for x in args.given_scales.split(",")]

    clips = eval_clips_from_dataset(args.shards, limit=args.limit)
    metas = _metas(args.shards, [c.key for c in clips])
    starts = [float(m["start_s"]) for m in metas]
    hazard = [bool(m.get("hazard")) for m in metas]
    wr = WorldRebuild(Path(args.world))
    vae = VideoVAE(encoded_with(args.checkpoint, args.shards), device="cpu")
    h_lat = 1 + (clips[0].num_history_frames - 1) // 4
    nh = clips[0].num_history_frames
    hw = clips[0].frames.shape[1:3]
    log(f"{len(clips)} clips of {len({c.item_id for c in clips})} episodes ({sum(hazard)} of hazardous explorers); "
        f"{len(K_GRID)} candidates each; given scales {scales}")
    given = {k: [scaled_trajectory(wr, c, t0, k) for c, t0 in zip(clips, starts)] for k in scales}
    dev = max(float(np.abs(g - c.trajectory).max()) for g, c in zip(given.get(1.0, []), clips)) if 1.0 in given else 0.0
    log(f"the rebuilt trajectory at scale 1 vs the shards': max |difference| {dev:.3f}")

    model, _ = load_world_model(args.checkpoint, "cpu", torch.float32)
    schedule = run_objective(args.checkpoint).schedule
    rc = {**ROLLOUT_PRESETS["resim"], "num_steps": args.steps, "guidance": guidance_preset("resim")}
    prompts = PromptSource(Path(args.shards), str(REPO / "configs/models/placeholder-t5-tiny"), device="cpu",
                           max_tokens=model.cfg.max_text_seq_length)
    runner = WorldRollouts(model, vae, from_dict(RolloutConfig, rc), lambda c: prompts(c), seed=args.seed,
                           schedule=schedule, log=log)
    t0 = time.perf_counter()
    gen = {k: runner.generate_latents(clips, given[k], [c.command for c in clips]).numpy() for k in scales}
    log(f"rollouts: {time.perf_counter() - t0:.0f} s")
    rec = np.stack([c.latents for c in clips])
    dec = runner.decode_recorded(clips)
    reenc = vae.encode(dec, [key_seed(c.key) for c in clips])   # the recorded latents through the VAE once more

    rows = []
    # the renders at the given scales: true videos of the clip driven at another speed, the IDMs' known answer
    k_at = {k: int(np.argmin(np.abs(K_GRID - k))) for k in scales}
    renders: dict = {k: {"video": [], "latent": []} for k in scales}
    t0 = time.perf_counter()
    for i, c in enumerate(clips):
        cand, ends, cand_videos = candidates(wr, c, starts[i], vae, hw)
        d_k = np.hypot(*ends.T)                     # each candidate's end-point distance at 4 s
        row = {"clip": c.key, "item_id": c.item_id, "hazard": hazard[i],
               "recorded_dist_m": float(np.hypot(*c.trajectory[-1, :2])),
               "render_dist_m": {f"{k:g}": float(d_k[j]) for k, j in k_at.items()}}
        if args.idm:
            for k, j in k_at.items():
                renders[k]["video"].append(cand_videos[j])
                renders[k]["latent"].append(cand[j])
        reads = [("recorded", rec[i]), ("recorded_reencoded", reenc[i])] + [(f"given_{k:g}", gen[k][i]) for k in scales]
        for name, lat in reads:
            k, contrast, per_frame = read_scale(lat, cand, h_lat)
            row[name] = {"k": round(k, 3), "contrast": round(contrast, 2),
                         "k_per_latent_frame": per_frame.round(2).tolist(), "dist_m": float(np.interp(k, K_GRID, d_k))}
            # the same read on the upper latent rows alone (sky, horizon, far scenery) and on the lower (road, near
            # scenery): a generated video need not be consistent, e.g. its road texture may flow at one speed while
            # its scenery comes closer at another; an IDM may read one of them, this reader both
            for region, rs in REGIONS.items():
                kr = read_scale(lat, cand, h_lat, rs)[0]
                row[name][f"dist_m_{region}"] = float(np.interp(kr, K_GRID, d_k))
        rows.append(row)
        log(f"clip {i + 1}/{len(clips)} {c.key[:44]}{' (explorer)' if hazard[i] else ''}: k read "
            + "  ".join(f"{n} {row[n]['k']:.2f} (x{row[n]['contrast']:.1f})" for n, _ in reads)
            + f"  ({time.perf_counter() - t0:.0f} s)")

    idm_reads = {}
    vids = {"recorded_video": np.stack([c.frames for c in clips]), "recorded_through_vae": dec,
            **{f"given_{k:g}": runner.decode(clips, torch.from_numpy(gen[k])) for k in scales},
            **{f"render_{k:g}": np.stack(renders[k]["video"]) for k in scales},
            **{f"render_{k:g}_through_vae": runner.decode(clips, torch.from_numpy(np.stack(renders[k]["latent"])))
               for k in scales}} if args.idm else {}
    for path in args.idm:
        idm = load_idm(path, "cpu")[0]
        idm_reads[path] = {n: np.hypot(*_idm_on(idm, v, nh)[:, -1, :2].T).round(3).tolist() for n, v in vids.items()}
    rep = {"world": args.world, "shards": args.shards, "checkpoint": args.checkpoint, "steps": args.steps,
           "seed": args.seed, "given_scales": scales, "k_grid": K_GRID.tolist(), "clips": rows,
           "idm_dist_at_4s_m": idm_reads, "summary": summarise(rows, scales, idm_reads)}
    (out / "render_match.json").write_text(json.dumps(rep, indent=1))
    print(json.dumps(rep["summary"], indent=1))
    plot(rows, scales, idm_reads, out / "render_match.png")
    return 0


def _metas(root, keys):
    m = {s["__key__"]: s["meta.json"] for s in iter_samples(root, attach_prompts=False)}
    return [m[k] for k in keys]


def _slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per clip (rows): least-squares slope of y on x."""
    xc = x - x.mean(axis=1, keepdims=True)
    return (xc * (y - y.mean(axis=1, keepdims=True))).sum(1) / (xc ** 2).sum(1)


def _ci(v: np.ndarray, n_boot: int = 2000) -> list[float]:
    rng = np.random.default_rng(0)
    b = [np.median(v[rng.integers(0, len(v), len(v))]) for _ in range(n_boot)]
    return [float(np.percentile(b, 2.5)), float(np.percentile(b, 97.5))]


def summarise(rows: list, scales: list[float], idm_reads: dict) -> dict:
    s: dict = {"n": len(rows), "explorer_clips": sum(r["hazard"] for r in rows)}
    s["reader_on_known_answers"] = {
        n: {"k_median": float(np.median([r[n]["k"] for r in rows])),
            "share_within_0.1_of_1": float(np.mean([abs(r[n]["k"] - 1) <= 0.1 for r in rows])),
            "contrast_median": float(np.median([r[n]["contrast"] for r in rows]))}
        for n in ("recorded", "recorded_reencoded")}
    for subset, keep in (("all", lambda r: True), ("expert_drivers", lambda r: not r["hazard"])):
        rr = [r for r in rows if keep(r)]
        if len(rr) < 2:
            continue
        x = np.array([[r["recorded_dist_m"] * k for k in scales] for r in rr])
        y = np.array([[r[f"given_{k:g}"]["dist_m"] for k in scales] for r in rr])
        sl = _slopes(x, y)
        regions = {}
        for region in REGIONS:
            yr = np.array([[r[f"given_{k:g}"][f"dist_m_{region}"] for k in scales] for r in rr])
            slr = _slopes(x, yr)
            regions[region] = {"render_read_dist_m_mean": yr.mean(0).round(2).tolist(),
                               "within_clip_slope_median": float(np.median(slr)), "within_clip_slope_ci95": _ci(slr)}
        d: dict = {"n": len(rr), "given_dist_m_mean": x.mean(0).round(2).tolist(),
                   "render_read_dist_m_mean": y.mean(0).round(2).tolist(),
                   "render_read_k_median": [float(np.median([r[f"given_{k:g}"]["k"] for r in rr])) for k in scales],
                   "contrast_median": [float(np.median([r[f"given_{k:g}"]["contrast"] for r in rr])) for k in scales],
                   "within_clip_slope_median": float(np.median(sl)), "within_clip_slope_ci95": _ci(sl),
                   "by_region (exploratory)": regions}
        idx = [rows.index(r) for r in rr]
        for path, reads in idm_reads.items():
            yi = np.array([[reads[f"given_{k:g}"][j] for k in scales] for j in idx])
            sli = _slopes(x, yi)
            d[f"idm {path}"] = {"read_dist_m_mean": yi.mean(0).round(2).tolist(),
                                "within_clip_slope_median": float(np.median(sli)), "within_clip_slope_ci95": _ci(sli),
                                "recorded_video_dist_m_mean": float(np.mean([reads["recorded_video"][j] for j in idx]))}
            # the IDM's known answer: true renders of the clip at the given scales, distance = the render's own
            xr = np.array([[rows[j]["render_dist_m"][f"{k:g}"] for k in scales] for j in idx])
            for suffix in ("", "_through_vae"):
                if f"render_{scales[0]:g}{suffix}" not in reads:
                    continue
                yr = np.array([[reads[f"render_{k:g}{suffix}"][j] for k in scales] for j in idx])
                slr = _slopes(xr, yr)
                d[f"idm {path}"][f"on_render{suffix}"] = {
                    "render_dist_m_mean": xr.mean(0).round(2).tolist(),
                    "read_dist_m_mean": yr.mean(0).round(2).tolist(),
                    "within_clip_slope_median": float(np.median(slr)), "within_clip_slope_ci95": _ci(slr)}
        s[subset] = d
    return s


def plot(rows: list, scales: list[float], idm_reads: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # a second row where the IDMs read the true renders too: the same IDM on true video of each speed (its known answer)
    on_renders = any(f"render_{scales[0]:g}_through_vae" in r for r in idm_reads.values())
    nrows = 2 if on_renders else 1
    fig, axes = plt.subplots(nrows, 1 + len(idm_reads), figsize=(4.2 * (1 + len(idm_reads)), 4 * nrows), squeeze=False)
    readers = [("re-rendering the world", lambda r, k, j: r[f"given_{k:g}"]["dist_m"])] + \
        [(f"IDM {Path(p).name}", lambda r, k, j, p=p: idm_reads[p][f"given_{k:g}"][j]) for p in idm_reads]
    for ax, (name, read) in zip(axes[0], readers):
        for j, r in enumerate(rows):
            xs = [r["recorded_dist_m"] * k for k in scales]
            ax.plot(xs, [read(r, k, j) for k in scales], "-o", ms=3, lw=0.8,
                    color="tab:red" if r["hazard"] else "tab:blue", alpha=0.7)
        lim = [0, max(r["recorded_dist_m"] for r in rows) * max(scales) * 1.1]
        ax.plot(lim, lim, "k:", lw=1)
        ax.set_xlabel("distance given at 4 s (m)")
        ax.set_ylabel("distance the rollout drove, read (m)")
        ax.set_title(f"read by {name}", fontsize=9)
    axes[0][0].text(0.02, 0.97, "blue: expert clips, red: explorers\none line per clip", transform=axes[0][0].transAxes,
                    va="top", fontsize=7)
    if on_renders:
        axes[1][0].axis("off")
        axes[1][0].text(0.05, 0.6, "this row: each IDM on the true renders\nof the clip at the given scales, through\n"
                        "the VAE (its known answer: on the\ndiagonal if it reads the motion)", fontsize=9, va="top")
        for ax, p in zip(axes[1][1:], idm_reads):
            for j, r in enumerate(rows):
                xs = [r["render_dist_m"][f"{k:g}"] for k in scales]
                ax.plot(xs, [idm_reads[p][f"render_{k:g}_through_vae"][j] for k in scales], "-o", ms=3, lw=0.8,
                        color="tab:red" if r["hazard"] else "tab:blue", alpha=0.7)
            lim = [0, max(max(r["render_dist_m"].values()) for r in rows) * 1.1]
            ax.plot(lim, lim, "k:", lw=1)
            ax.set_xlabel("distance of the true render at 4 s (m)")
            ax.set_ylabel("distance read (m)")
            ax.set_title(f"IDM {Path(p).name} on the true renders, through the VAE", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
