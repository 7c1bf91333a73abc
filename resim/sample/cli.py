"""`resim sample` (roll the world model out from a history) and `resim plan` (rank candidate trajectories by the
reward of their imagined futures). Light module: every `resim` call imports this module to register its
subcommands, so what needs torch, numpy or the models is imported inside the handler that uses it, to keep
`resim --help` fast.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from resim.argtypes import add_settings_args, local_dir, positive_float, positive_int, torch_device
from resim.config import ConfigError, save, to_dict
from resim.shards.schema import latent_frame_count, pixel_frame_count, temporal_compression_of


SAMPLE_EPILOG = """\
examples:
  resim sample --checkpoint runs/wm --history clip.mp4 --command "Turning left" --seconds 4 --out out/s1
  resim sample --checkpoint runs/wm --shards out/shards --history KEY --trajectory turn_right --out out/s2
  resim sample ... --command "Moving forward" --command "Turning left" --seconds 8    # one command per 4-s round
  resim sample ... --preset vid2world --set runtime.actions_from_trajectory=true     # frame by frame + actions

History: a video file (resampled to the model's training clip rate, 10 Hz for CogVideoX-style video sources; its
last 1 + r (N - 1) frames, N = rollout.history_frames (default 3), r = the VAE's temporal ratio (4: 9 frames; 1: 3
frames), are encoded with --vae; files below that rate
are refused) or, with --shards, a sample key (its stored history latents, at the shard's rate: --seconds and the
actions follow it). A key's clip must hold N latent history frames: video sources (OpenDV, CARLA) keep 9 pixel
frames = 3; a NAVSIM key keeps 1 (2 Hz), so sample it with --set rollout.history_frames=1.
--command / --trajectory may be repeated: round r uses the r-th (the last one repeats).
Settings beyond the flags (--set KEY=VALUE, or a --config YAML file with these sections):
  rollout.chunk_frames (default: the preset's, 10 resim / 1 vid2world), rollout.history_frames (3 = 9 video
  frames; 1 for a NAVSIM shard key), rollout.history_noise_level (0 = clean), rollout.kv_cache (auto|on|off),
  rollout.guidance.scale_start / .schedule (linear|constant|cosine);
  runtime.text_encoder (local T5 folder for prompts not in a table), runtime.max_text_tokens (226),
  runtime.size_hw ([H, W] of a video history; default the model's training clips'), runtime.dtype
  (float32|bfloat16|float16), runtime.attention (sdpa|flex), runtime.compile (auto|on|off; auto: CUDA only),
  runtime.compile_mode, runtime.actions_from_trajectory (also feed per-frame actions; action-conditioned models).
A trajectory is a candidate name (keep_lane, turn_left, turn_right, brake, swerve), an (8, 3) .npy file, a .json
file or inline JSON [[x_m, y_m, yaw_rad], ...] at 0.5 s steps in the ego frame (x forward, y left).
--vae and runtime.text_encoder are local folders (nothing is downloaded).
Writes DIR/sample.mp4, .gif, _sheet.png, _latents.npy (exact float32 latents: compare runs bit for bit),
_meta.json, rollout.yaml (the resolved sampling config) and run.json (checkpoint, history, seed, device, dtype,
VAE, prompt sources, timings).
"""

PLAN_EPILOG = """\
example:
  resim plan --checkpoint runs/wm --reward runs/reward --shards out/shards --history KEY --out out/plan

Rolls out every candidate (default: keep_lane turn_left turn_right brake swerve) from the same history with
the same noise, scores each imagined future with Video2Reward and writes DIR/ranking.md, ranking.json,
plan_grid.png (one row per candidate, best first, with its reward), plan_latents.npy, rollout.yaml and run.json.
--reward is a `resim train reward` run folder (checked before the world model is loaded). History, --vae,
--device, --set etc. as for `resim sample` (see its --help).
"""


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True,
                   help="world-model run dir (or its final/ folder), or a shipped model name (synth-world)")
    p.add_argument("--history", required=True, help="a video file, or a shard sample key (with --shards)")
    p.add_argument("--shards", default=None, help="dataset folder holding the history key (and prompt table)")
    p.add_argument("--seconds", type=positive_float, default=4.0, help="future to generate, seconds > 0 (default 4)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the rollout's noise: the same seed, inputs and device give the same latents "
                        "(default 0)")
    p.add_argument("--preset", default="resim", choices=["resim", "vid2world"],
                   help="resim: 10-frame chunks, CFG 7.5->1; vid2world: frame by frame, action guidance 2.5, "
                        "rescale 0.7 (default resim)")
    p.add_argument("--steps", type=positive_int, default=None,
                   help="DDIM steps >= 1 (default 50; a distilled student: its own, e.g. 4)")
    p.add_argument("--no-guidance", action="store_true", help="conditional branch only")
    p.add_argument("--vae", type=local_dir, default=None,
                   help="local CogVideoX VAE folder (default: the VAE that encoded the model's training data, "
                        "from --shards or the checkpoint's final/data_encode.yaml)")
    p.add_argument("--device", type=torch_device, default=None, help="cpu, cuda or cuda:N (default: cuda if available)")
    add_settings_args(p)
    p.add_argument("--out", required=True, help="output folder")


def register(subparsers) -> None:
    p = subparsers.add_parser("sample", help="roll a trained world model out from a history",
                              description="Generate the future of a history with the world model (guided DDIM, "
                                          "chunked causal rollout with a KV cache, any horizon).",
                              epilog=SAMPLE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _common(p)
    p.add_argument("--command", action="append", default=None,
                   help='driving command per round: "Turning left", "Moving forward", "Turning right"')
    p.add_argument("--trajectory", action="append", default=None, help="trajectory per round (see below)")
    p.set_defaults(func=_cmd_sample)

    q = subparsers.add_parser("plan", help="rank candidate trajectories by the reward of their imagined futures",
                              description="ReSim-style planning: roll out K candidate trajectories, score each "
                                          "imagined future with Video2Reward, rank them.",
                              epilog=PLAN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _common(q)
    q.add_argument("--reward", required=True, help="Video2Reward checkpoint folder (a `resim train reward` run)")
    q.add_argument("--candidates", nargs="+", default=None,
                   help="candidate names (default: keep_lane turn_left turn_right brake swerve)")
    q.add_argument("--speed-mps", type=positive_float, default=8.0,
                   help="speed of the candidate paths, m/s > 0 (default 8)")
    q.set_defaults(func=_cmd_plan)


# ----------------------------------------------------------------------------------------------- checks
class UsageError(Exception):
    """A mistake on the command line, found before (or instead of) loading a model: one line, exit 2."""


def make_out(out: str | Path) -> Path:
    """Create ``--out`` and return it; :class:`UsageError` naming it when it is a file, lies inside a dataset (a
    folder with ``shards/`` and ``index/``, itself or above: rollouts written there would sit among its shards),
    or cannot be created (read-only, no permission, disk full)."""
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise UsageError(f"--out {p} is a file, not a folder")
    for d in (p.absolute(), *p.absolute().parents):
        if (d / "shards").is_dir() and (d / "index").is_dir():
            raise UsageError(f"--out {p} lies inside the dataset {d}; write rollouts outside it, so the dataset "
                             "stays as `resim pipeline run` made it")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"--out {p}: cannot be created ({e.strerror})") from None
    return p


def resolve_device(device: str | None) -> str:
    """``--device`` (already spelt right, see ``resim.argtypes.torch_device``) → a device this torch build can use
    (``resim.media.device``); :class:`UsageError` naming it otherwise."""
    from resim.media import device as media_device   # imports torch: this module stays light (see the top)

    try:
        return media_device.resolve_device(device, flag="--device")
    except media_device.DeviceError as e:
        raise UsageError(str(e)) from None


def _trajectories(specs: list[str] | None) -> list:
    """``--trajectory`` values → (N, 3) arrays; a path that is not there is "no such file", not a JSON error."""
    from resim.sample.load import SamplingInputError, load_trajectory
    from resim.sample.plan import CANDIDATE_NAMES

    kinds = f"a candidate name ({', '.join(CANDIDATE_NAMES)}), an (8, 3) .npy file, a .json file or inline JSON"
    out = []
    for spec in specs or []:
        p = Path(spec)
        if spec not in CANDIDATE_NAMES and not spec.lstrip().startswith("["):
            looks_like_path = p.suffix.lower() in (".npy", ".json") or "/" in spec or "\\" in spec
            if looks_like_path and not p.is_file():
                raise UsageError(f"--trajectory {spec}: no such file (give {kinds})")
        try:
            out.append(load_trajectory(spec))
        except SamplingInputError as e:
            raise UsageError(str(e)) from None
        except (ValueError, OSError) as e:   # np.load of a file that is not a .npy array
            raise UsageError(f"--trajectory {spec}: not a readable .npy array ({e})") from None
    return out


def _check_args(args, command: str):
    """Everything about the command line that needs no model: returns (device, settings, trajectories)."""
    from resim.sample.settings import resolve_settings

    settings = resolve_settings(args)   # ConfigError: one line naming the key
    trajectory = getattr(args, "trajectory", None)
    from_traj = settings.runtime.actions_from_trajectory
    if command == "sample" and from_traj and not trajectory:
        raise UsageError("runtime.actions_from_trajectory derives the actions from a trajectory: add --trajectory")
    if args.preset == "vid2world" and settings.rollout.guidance.enabled and not from_traj:
        raise UsageError("--preset vid2world guides on actions; add --set runtime.actions_from_trajectory=true "
                         "(and --trajectory) or --no-guidance")
    if not Path(args.history).is_file():
        if not args.shards:
            raise UsageError(f"--history {args.history}: not a file; to use a shard sample key pass "
                             "--shards DATASET_DIR")
        if not Path(args.shards).is_dir():
            raise UsageError(f"--shards {args.shards}: no such folder")
    trajs = _trajectories(trajectory)
    from resim.sample.load import _checkpoint_dir
    _checkpoint_dir(args.checkpoint)   # the world-model checkpoint's files exist
    return resolve_device(args.device), settings, trajs


def _shard_history_frames(root: str, key: str) -> tuple[int, int, float] | None:
    """(latent history frames, pixel history frames, fps) of a shard sample, or None if it cannot be read."""
    try:
        from resim.shards.reader import find_sample
        s = find_sample(root, key, decode_video=False, attach_prompts=False)
        meta, px = s["meta.json"], int(s["meta.json"]["num_history_frames"])
        tc = temporal_compression_of(int(meta["num_frames"]), len(s["latent.npy"]))
        return latent_frame_count(px, tc), px, float(meta["fps_hz"])
    except Exception:   # only for a better message; the original error is raised when this fails
        return None


# ----------------------------------------------------------------------------------------------- set-up
class _Setup:
    """Everything both commands build from the common arguments (after :func:`_check_args`)."""

    def __init__(self, args, device: str, settings):
        from resim.sample.bundle import WorldModelBundle
        from resim.sample.load import PromptSource, SamplingInputError, trained_size_hw
        from resim.sample.rollout import rollout_num_future_frames

        self.device = device
        rt = self.runtime = settings.runtime
        self.cfg, self.settings = settings.rollout, settings
        # the model, its objective (its schedule is what DDIM steps over), the VAE that encoded its training data;
        # the settings' dtype, kernel and compile applied, steps and levels checked against the run's schedule
        self.bundle = WorldModelBundle.for_rollout(args.checkpoint, settings, device=device, vae=args.vae,
                                                   shards=args.shards, log=lambda m: print(f"[resim] {m}",
                                                                                           file=sys.stderr))
        self.model, self.objective, self.vae = self.bundle.model, self.bundle.objective, self.bundle.vae
        self.model_info = self.bundle.info
        if Path(args.history).is_file():
            # the size the model's training clips were encoded at (its data's encode section), else its sample size
            trained = trained_size_hw(args.checkpoint, args.shards)
            if rt.size_hw and trained and tuple(rt.size_hw) != trained:
                raise UsageError(f"runtime.size_hw={list(rt.size_hw)}: the model was trained on {trained[0]}x"
                                 f"{trained[1]} clips (its training data's encode size); leave it out or give "
                                 f"[{trained[0]}, {trained[1]}]")
            size = tuple(rt.size_hw) if rt.size_hw else self.bundle.size_hw
            sc = self.vae.info.spatial_compression
            mult = sc * int(getattr(self.model.cfg, "patch_size", 1) or 1)
            if size[0] % mult or size[1] % mult:
                ms = self.bundle.size_hw
                raise UsageError(f"runtime.size_hw={list(size)}: both sides must be multiples of {mult} (the VAE's "
                                 f"{sc}x downsampling times the model's patch size), e.g. the model's sample size "
                                 f"{ms[0]}x{ms[1]}")
            self.history = self.bundle.history(args.history, self.cfg.history_frames, size)
        else:
            try:
                self.history = self.bundle.history(args.history, self.cfg.history_frames)
            except SamplingInputError:
                have = _shard_history_frames(args.shards, args.history)
                if have is None or have[0] >= self.cfg.history_frames:
                    raise
                h, px, fps = have
                raise SamplingInputError(
                    f"history {args.history!r}: its clip holds {h} latent history frame(s) ({px} pixel frames at "
                    f"{fps:g} Hz), the rollout keeps {self.cfg.history_frames}: pass --set rollout.history_frames={h}, "
                    f"or use a clip with {self.cfg.history_frames} latent history frames (a video source)") from None
        self.prompts = PromptSource(self.history.prompt_root, rt.text_encoder, device=self.device,
                                    max_tokens=rt.max_text_tokens)
        self.num_future = rollout_num_future_frames(args.seconds, self.history.fps_hz, self.vae.info.temporal_compression)
        # seconds one latent frame spans: the same formula as training's Batch.latent_frame_dt_s (temporal
        # compression / the clip's fps): 0.4 s for a 10 Hz history, 2 s for a NAVSIM (2 Hz) shard history
        self.latent_frame_dt_s = self.vae.info.temporal_compression / self.history.fps_hz
        self.waypoint_dt_s = getattr(getattr(self.model, "objective", None), "waypoint_dt_s", 0.5)
        self.actions_from_trajectory = rt.actions_from_trajectory
        self.args = args

    def text_for(self, command):
        t = self.prompts(command)
        if t.shape[-1] != self.model.cfg.text_embed_dim:
            raise SystemExit(f"resim: prompt embedding dim {t.shape[-1]} != the model's text_embed_dim "
                             f"{self.model.cfg.text_embed_dim} (wrong runtime.text_encoder or prompt table)")
        return t.to(self.device)

    def policy_for(self, trajs_per_round):
        """A policy feeding actions derived from each round's trajectory (Vid2World-style conditioning), as
        training derives them (``resim.diffusion.losses``: the clip's latent frame duration, the objective's
        waypoint spacing); frames past the trajectory's horizon get the null action (invalid), as in training."""
        if not self.actions_from_trajectory:
            return None
        from resim.models.world.conditioning import actions_from_trajectory
        cfg = self.cfg

        def policy(inp):
            traj = trajs_per_round(inp.round_index)
            if traj is None:
                raise SystemExit("resim: runtime.actions_from_trajectory needs a --trajectory")
            # offset of this chunk inside its round (rounds start right after the given history)
            off = (inp.frame_index - self.history.latents.shape[1]) % cfg.frames_per_round
            acts, valid = actions_from_trajectory(traj.float(), cfg.frames_per_round, 0, self.latent_frame_dt_s,
                                                  self.waypoint_dt_s)
            sl = slice(off, off + inp.num_frames)
            return acts[:, sl].to(self.device), valid[:, sl].to(self.device)
        return policy

    def progress(self, total: int, desc: str):
        from tqdm import tqdm
        return tqdm(total=total, desc=desc, unit="step", file=sys.stderr, dynamic_ncols=True)


def _save_config(setup: _Setup, out: Path, extra: dict) -> None:
    save(setup.cfg, out / "rollout.yaml")
    (out / "run.json").write_text(json.dumps({**setup.model_info, "history": setup.history.source,
                                              "seconds": setup.args.seconds, "seed": setup.args.seed,
                                              "history_fps_hz": setup.history.fps_hz,
                                              "latent_frame_dt_s": setup.latent_frame_dt_s,
                                              "device": setup.device, "dtype": setup.runtime.dtype,
                                              "runtime": to_dict(setup.runtime),
                                              "vae_id": setup.vae.info.vae_id,
                                              "vae_placeholder": setup.vae.info.placeholder,
                                              "prompts": setup.prompts.used, "rollout": to_dict(setup.cfg),
                                              **extra}, indent=2, default=str))


# ----------------------------------------------------------------------------------------------- sample
def _cmd_sample(args) -> int:
    import torch

    from resim.shards.schema import COMMANDS
    from resim.sample.load import SamplingInputError
    from resim.sample.outputs import decode_rollout, write_rollout
    from resim.sample.rollout import Condition, rollout, rollout_num_steps_total

    for c in args.command or []:
        if c not in COMMANDS:
            print(f"resim sample: --command {c!r} is not one of {list(COMMANDS)}", file=sys.stderr)
            return 2
    t_start = time.perf_counter()
    try:
        device, settings, trajs = _check_args(args, "sample")   # no model is loaded for a command-line mistake
        _say("sample")("loading the world model and VAE, reading the history ...")
        s = _Setup(args, device, settings)
        enc = getattr(s.model, "trajectory_encoder", None)
        want = (enc.cfg.num_waypoints, enc.cfg.waypoint_dim) if enc is not None else None
        for spec, t in zip(args.trajectory or [], trajs):
            if want is not None and tuple(t.shape) != want:
                raise UsageError(f"--trajectory {spec if len(spec) < 60 else spec[:57] + '...'}: the model takes "
                                 f"{want[0]} waypoints of {want[1]} values, got shape {tuple(t.shape)}")
        out = make_out(args.out)
    except (UsageError, SamplingInputError, ConfigError) as e:
        print(f"resim sample: {e}", file=sys.stderr)
        return 2
    commands = args.command or [None]
    try:   # every prompt now, before the progress bar: an unusable prompt table (an entry outside prompts/, ...)
        texts = {c: s.text_for(c) for c in dict.fromkeys([None, *commands])}
    except SamplingInputError as e:
        print(f"resim sample: {e}", file=sys.stderr)
        return 2
    null = texts[None]

    def traj_at(r):
        if not trajs:
            return None
        return torch.from_numpy(trajs[min(r, len(trajs) - 1)])[None].to(s.device)

    def cond_at(r):
        cmd = commands[min(r, len(commands) - 1)]
        return Condition(text=texts[cmd], null_text=null, trajectory=traj_at(r), label=cmd or "(no command)")

    total = rollout_num_steps_total(s.cfg, s.num_future, s.objective.schedule)
    t0 = time.perf_counter()
    with s.progress(total, "sampling") as bar:
        res = rollout(s.model, s.history.latents.to(s.device), cond_at, s.num_future, s.cfg, seed=args.seed,
                      policy=s.policy_for(traj_at), progress=bar, actions_from_trajectory=s.actions_from_trajectory,
                      schedule=s.objective.schedule)
    if not bool(torch.isfinite(res.latents).all()):   # finite inputs and weights, and still: say so, write nothing
        n = int((~torch.isfinite(res.latents)).sum())
        print(f"resim sample: the rollout holds {n} NaN/inf values of {res.latents.numel()} (finite history, prompts "
              f"and weights: the model overflowed); nothing written", file=sys.stderr)
        return 1
    t_setup = t0 - t_start
    _say("sample")("decoding the rollout with the VAE, writing the video ...")
    frames = decode_rollout(s.vae, res.latents, res.num_history_frames, s.cfg.frames_per_round,
                            s.cfg.history_frames)[0]
    num_hist_px = pixel_frame_count(res.num_history_frames, s.vae.info.temporal_compression)
    title = " | ".join(dict.fromkeys(res.round_labels)) + f"   ({args.seconds:g} s, seed {args.seed})"
    paths = write_rollout(out, "sample", frames, res.latents[0].cpu().numpy(), num_history_px=num_hist_px,
                          fps_hz=s.history.fps_hz, title=title,
                          trajectory=trajs[0] if trajs else None,
                          meta={"round_labels": res.round_labels, "kv_cache": res.kv_cache_used,
                                "placeholder_vae": s.vae.info.placeholder})
    _save_config(s, out, {"rollout_seconds": res.seconds, "model_forwards": res.model_forwards})
    print(f"sampled {s.num_future} latent frames ({frames.shape[0] - num_hist_px} video frames, "
          f"{len(res.round_labels)} round(s)) in {res.seconds:.1f} s "
          f"({res.model_forwards} model calls, KV cache {'on' if res.kv_cache_used else 'off'}); "
          f"total {time.perf_counter() - t_start:.1f} s wall clock (set-up and history {t_setup:.1f} s, "
          f"decoding and writing {time.perf_counter() - t0 - res.seconds:.1f} s)")
    for k in ("mp4", "gif", "sheet", "latents"):
        print(f"  {k:8s} {paths[k]}")
    if s.vae.info.placeholder:
        print("  note: the VAE is a random-init placeholder: pixels are not meaningful")
    return 0


def _say(cmd: str, bar=None):
    """A one-line progress message on stderr (through the progress bar when one is open, so it is not torn)."""
    from tqdm import tqdm

    def say(message: str) -> None:
        line = f"[resim {cmd}] {message}"
        if bar is not None:
            tqdm.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)
    return say


# ----------------------------------------------------------------------------------------------- plan
def _cmd_plan(args) -> int:
    import numpy as np

    from resim.models.reward.checkpoint import CheckpointError, load_checkpoint
    from resim.sample.load import SamplingInputError
    from resim.sample.outputs import grid_with_scores
    from resim.sample.plan import CANDIDATE_NAMES, default_candidates, plan
    from resim.sample.rollout import rollout_num_steps_total

    names = args.candidates or list(CANDIDATE_NAMES)
    bad = [n for n in names if n not in CANDIDATE_NAMES]
    if bad:
        print(f"resim plan: unknown candidate(s) {bad}; known: {', '.join(CANDIDATE_NAMES)}", file=sys.stderr)
        return 2
    try:
        device, settings, _ = _check_args(args, "plan")
        try:   # the reward model first: it loads in a moment, the world model and VAE take longer
            reward = load_checkpoint(args.reward, device=device)
        except CheckpointError as e:
            raise UsageError(f"--reward: {e}") from None
        s = _Setup(args, device, settings)
        out = make_out(args.out)
    except (UsageError, SamplingInputError, ConfigError) as e:
        print(f"resim plan: {e}", file=sys.stderr)
        return 2
    cands = default_candidates(args.speed_mps, names)
    total = rollout_num_steps_total(s.cfg, s.num_future, s.objective.schedule)
    try:   # every prompt now, before the progress bar: an unusable prompt table (an entry outside prompts/, ...)
        texts = {c: s.text_for(c) for c in dict.fromkeys([None, *(c.command for c in cands)])}
    except SamplingInputError as e:
        print(f"resim plan: {e}", file=sys.stderr)
        return 2
    with s.progress(total, f"imagining {len(cands)} futures") as bar:
        policy_for = (lambda trajs: s.policy_for(lambda r: trajs)) if s.actions_from_trajectory else None
        res = plan(s.model, reward, s.vae, s.history.latents.to(s.device), texts.__getitem__, cands, s.cfg,
                   s.num_future, seed=args.seed, policy_for=policy_for, progress=bar,
                   actions_from_trajectory=s.actions_from_trajectory, log=_say("plan", bar),
                   schedule=s.objective.schedule)
    bad = [r.name for r in res.rows if not (np.isfinite(r.latents).all() and np.isfinite(r.score))]
    if bad:   # finite inputs and weights, and still: say so, write nothing
        print(f"resim plan: the rollouts of {', '.join(bad)} hold NaN/inf values (finite history, prompts and "
              f"weights: the model overflowed); nothing written", file=sys.stderr)
        return 1
    table = res.table()
    (out / "ranking.md").write_text(table + "\n")
    (out / "ranking.json").write_text(json.dumps(
        [{"rank": r.rank, "name": r.name, "command": r.command, "reward": r.score,
          "trajectory": np.asarray(r.trajectory).tolist()} for r in res.rows], indent=2))
    grid = grid_with_scores([{"name": r.name, "score": r.score, "rank": r.rank, "frames": r.frames,
                              "num_history_px": res.num_history_px, "trajectory": r.trajectory}
                             for r in res.rows], s.history.fps_hz)
    grid.save(out / "plan_grid.png")
    np.save(out / "plan_latents.npy", np.stack([r.latents for r in res.rows]).astype(np.float32))
    _save_config(s, out, {"reward": str(args.reward), "reward_meta": reward.metadata(),
                          "candidates": [r.name for r in res.rows], "rollout_seconds": res.seconds})
    print(table)
    print(f"best: {res.rows[0].name} (reward {res.rows[0].score:.4f}); {len(cands)} futures in {res.seconds:.1f} s")
    print(f"  grid     {out / 'plan_grid.png'}\n  ranking  {out / 'ranking.md'}")
    if reward.metadata().get("backbone_placeholder") or s.vae.info.placeholder:
        print("  note: placeholder (random-init) VAE/backbone in use: scores rank imagined pixels of a toy setup")
    return 0
