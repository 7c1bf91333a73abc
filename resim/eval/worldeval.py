"""World-model evaluations on held-out clips: controllability, planning, video quality.

All three roll the world model out with the sampler (``resim.sample.rollout``) from each clip's history
latents, decode the latents with the VAE (``resim.sample.outputs.decode_rollout``) and compare with the
clip's recorded frames / trajectory:

* :func:`control_eval` (ReSim's *Trajectory Difference*): (a) conditioned on the clip's recorded trajectory
  and command (expert action), (b) on the trajectory and command of another clip (non-expert action,
  drawn from another episode with a seeded RNG); the IDM reads the trajectory off each generated video, the
  report gives its L2 to the conditioning trajectory (mean over waypoints, and at 4 s), plus, when the
  optical-flow labeler (``labeling``) is importable, the share of generated videos whose flow
  command equals the conditioning command. The IDM's error on the *recorded* video of the same clips is the
  floor the generated numbers should be read against; on the recorded latents decoded through the VAE, the
  floor of any model that generates through that VAE. ``followed`` splits the distance into speed and turn.
* :func:`planning_eval` (ReSim's video-prediction policy): rollout with no trajectory and the null prompt
  (no action condition), IDM on the predicted future → trajectory; baselines: the VO-style planner (the
  IDM's architecture on history frames only) and constant velocity; ADE/FDE against the recorded future.
* :func:`quality_eval`: rollouts under the recorded trajectory and command vs the recorded frames through
  :class:`resim.eval.quality.VideoQualityEvaluator` (history frames excluded), per horizon.

Frames generated at the VAE's resolution are compared with ``frames.mp4`` after resizing both to the
evaluation resolution (the protocol says which); the IDM resizes its input itself.
"""
from __future__ import annotations

import hashlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from resim.eval.quality import VideoQualityEvaluator
from resim.labeling.config import preset as labeler_preset
from resim.labeling.flow import FlowLabeler
from resim.sample.outputs import decode_rollout
from resim.sample.rollout import Condition, rollout
from resim.shards.reader import iter_samples
from resim.shards.schema import latent_frame_count, temporal_compression_of
from resim.train.tasks.idm import constant_velocity, resize_frames, trajectory_errors


@dataclass
class EvalClip:
    key: str
    item_id: str
    latents: np.ndarray           # (T_lat, C, h, w) float32, VAE latents x scaling factor
    frames: np.ndarray            # (T, H, W, 3) uint8 RGB (frames.mp4)
    trajectory: np.ndarray | None # (8, 3) float32
    command: str | None
    num_history_frames: int
    fps_hz: float
    vae_placeholder: bool
    temporal_compression: int = 4  # pixel frames per latent frame after the first, as the dataset's VAE encoded it

    @property
    def num_history_latents(self) -> int:
        return latent_frame_count(self.num_history_frames, self.temporal_compression)


def eval_clips_from_dataset(root: str | Path, *, items: Sequence[str] | None = None, limit: int | None = None,
                            need_trajectory: bool = True, fits: Callable[[EvalClip], bool] | None = None
                            ) -> list[EvalClip]:
    """Clips of ``root`` (only those of episodes ``items`` when given; at most ``limit``, spread over the
    episodes by :func:`spread_over_episodes`; ``None``: all). ``fits``: keep the clips a reader can read (e.g.
    :func:`idm_fits`: an IDM's frame window) before the most common geometry is chosen, unless none fits (the
    caller's own check then names the reason)."""
    # `limit is not None`, not `if limit`: a limit of 0 must not mean "all clips"
    if limit is not None and limit < 1:
        raise ValueError(f"limit must be >= 1 (or None for all clips), got {limit}")
    if not Path(root).is_dir():
        raise FileNotFoundError(f"dataset folder {root} does not exist")
    keep = set(items) if items is not None else None
    out = []
    for s in iter_samples(root, decode_video=True, attach_prompts=False):
        m = s["meta.json"]
        if keep is not None and m["item_id"] not in keep:
            continue
        if need_trajectory and "traj.npy" not in s:
            continue
        lat = np.asarray(s["latent.npy"], np.float32)
        out.append(EvalClip(s["__key__"], m["item_id"], lat, s["frames"],
                            np.asarray(s["traj.npy"], np.float32) if "traj.npy" in s else None, m.get("command"),
                            int(m["num_history_frames"]), float(m["fps_hz"]), bool(m.get("vae_placeholder")),
                            temporal_compression_of(int(m["num_frames"]), len(lat))))
    out.sort(key=lambda c: c.key)
    if fits is not None:
        out = [c for c in out if fits(c)] or out
    out = _one_geometry(out)
    return spread_over_episodes(out, limit) if limit is not None else out


def spread_over_episodes(clips: list[EvalClip], limit: int) -> list[EvalClip]:
    """At most ``limit`` clips taken round-robin over the episodes (each episode's clips in key order).

    Keys group clips by episode, so the first ``limit`` keys would often be one episode: too few for
    non-expert trajectories (taken from another episode) and a poor sample of the set. Returned in key order."""
    by_ep: dict[str, list[EvalClip]] = {}
    for c in clips:
        by_ep.setdefault(c.item_id, []).append(c)
    queues, picked = list(by_ep.values()), []
    while len(picked) < limit and any(queues):
        for q in queues:
            if q and len(picked) < limit:
                picked.append(q.pop(0))
    return sorted(picked, key=lambda c: c.key)


def _one_geometry(clips: list[EvalClip]) -> list[EvalClip]:
    """Keep the most common clip geometry (latent shape, history frames, fps).

    A dataset can mix geometries (NAVSIM-style 2 Hz clips next to 10 Hz ones); one rollout batch and one
    IDM window need one geometry, so the others are left out, and said so, rather than failing mid-run.
    """
    if not clips:
        return clips
    geo = lambda c: (tuple(c.latents.shape), c.num_history_frames, c.fps_hz)  # noqa: E731
    counts: dict = {}
    for c in clips:
        counts[geo(c)] = counts.get(geo(c), 0) + 1
    best = max(counts, key=lambda g: (counts[g], g[0][0]))
    if len(counts) > 1:
        others = ", ".join(f"{n} x latent {g[0]} @ {g[2]:g} Hz" for g, n in counts.items() if g != best)
        print(f"[resim eval] evaluating the {counts[best]} clips of geometry latent {best[0]} @ {best[2]:g} Hz; "
              f"left out clips of other geometries: {others}", file=sys.stderr)
    return [c for c in clips if geo(c) == best]


class WorldRollouts:
    """Rolls the world model out for batches of clips and decodes the result to pixels.

    ``text_for(command | None) -> (1, L, D)`` gives prompt embeddings (``None``: the prefix-only null prompt),
    e.g. a ``resim.sample.load.PromptSource``.
    """

    def __init__(self, model: Any, vae: Any, rollout_cfg: Any, text_for: Callable[[str | None], torch.Tensor],
                 device: str = "cpu", seed: int = 0, batch_size: int = 4, schedule: Any = None,
                 log: Callable[[str], None] | None = None, log_every_s: float = 60.0):
        """``schedule``: the run's noise schedule (``run_objective(checkpoint).schedule``). ``log``: called with a
        progress line (rollouts so far, seconds) after a batch, at most every ``log_every_s`` seconds: a 50-step
        evaluation on a CPU otherwise says nothing for a quarter of an hour."""
        self.model, self.vae, self.cfg, self.text_for = model, vae, rollout_cfg, text_for
        self.schedule = schedule
        self.device, self.seed, self.batch_size = device, seed, batch_size
        self.rollouts = 0
        self.log, self.log_every_s = log, log_every_s
        self._t0 = self._last_log = time.perf_counter()

    def history_latents(self, clip: EvalClip) -> int:
        return clip.num_history_latents

    def generate(self, clips: Sequence[EvalClip], trajectories: Sequence[np.ndarray | None],
                 commands: Sequence[str | None], offset: int = 0,
                 num_future_latents: int | None = None) -> np.ndarray:
        """Decoded videos ``(N, T, H, W, 3)`` uint8 (history then generated frames, the clip's length, or
        ``num_future_latents`` generated latent frames when given: a longer autoregressive rollout).

        The batch starting at clip ``i`` of the whole evaluation set is sampled with seed ``seed + i``;
        ``offset`` is the position of ``clips[0]`` in that set, for callers that pass it in parts (e.g.
        :func:`quality_eval`): without it every part would restart at ``seed`` and draw the same starting
        noise, correlating the samples that FID/FVD assume independent."""
        return self.decode(clips, self.generate_latents(clips, trajectories, commands, offset, num_future_latents))

    def generate_latents(self, clips: Sequence[EvalClip], trajectories: Sequence[np.ndarray | None],
                         commands: Sequence[str | None], offset: int = 0,
                         num_future_latents: int | None = None) -> torch.Tensor:
        """The rollouts of :meth:`generate` before decoding: ``(N, H + F, C, h, w)`` float32 latents, history then
        generated frames (same seeds as ``generate``)."""
        out = []
        for i in range(0, len(clips), self.batch_size):
            out.append(self._batch(clips[i:i + self.batch_size], trajectories[i:i + self.batch_size],
                                   commands[i:i + self.batch_size], seed=self.seed + offset + i,
                                   num_future_latents=num_future_latents))
        return torch.cat(out)

    def decode(self, clips: Sequence[EvalClip], latents: torch.Tensor) -> np.ndarray:
        """Rollout latents ``(N, H + F, C, h, w)`` of ``clips`` → videos ``(N, T, H, W, 3)`` uint8, round by round
        as the sampler decodes (``decode_rollout``)."""
        h = self.history_latents(clips[0])
        out = [decode_rollout(self.vae, latents[i:i + self.batch_size].to(self.device), h, self.cfg.frames_per_round,
                              self.cfg.history_frames, batch_size=self.batch_size)
               for i in range(0, len(clips), self.batch_size)]
        return np.concatenate(out)

    def _batch(self, clips, trajs, commands, seed: int, num_future_latents: int | None = None) -> torch.Tensor:
        h = self.history_latents(clips[0])
        t_lat = clips[0].latents.shape[0]
        if any(c.latents.shape[0] != t_lat or self.history_latents(c) != h for c in clips):
            raise ValueError("clips of one batch must share their geometry")
        hist = torch.from_numpy(np.stack([c.latents[:h] for c in clips])).to(self.device)
        text = torch.cat([self.text_for(c) for c in commands]).to(self.device)
        null = torch.cat([self.text_for(None) for _ in commands]).to(self.device)
        if all(t is None for t in trajs):
            traj = None
        elif any(t is None for t in trajs):
            raise ValueError("a batch mixes clips with and without a conditioning trajectory")
        else:
            traj = torch.from_numpy(np.stack(trajs)).float().to(self.device)
        cond = Condition(text=text, null_text=null, trajectory=traj)
        res = rollout(self.model, hist, cond, t_lat - h if num_future_latents is None else num_future_latents,
                      self.cfg, seed=seed, schedule=self.schedule)
        self.rollouts += len(clips)
        now = time.perf_counter()
        if self.log is not None and now - self._last_log >= self.log_every_s:
            self._last_log = now
            self.log(f"{self.rollouts} rollouts so far, {now - self._t0:.0f} s "
                     f"({(now - self._t0) / self.rollouts:.1f} s each)")
        return res.latents.cpu()

    def decode_recorded(self, clips: Sequence[EvalClip]) -> np.ndarray:
        """The clips' own latents decoded as a rollout's are (``decode_rollout``, round by round): the video a
        world model that predicted the recorded future exactly would show, ``(N, T, H, W, 3)`` uint8."""
        return self.decode(clips, torch.from_numpy(np.stack([c.latents for c in clips])))


def _idm_on(idm, videos: np.ndarray, num_history_frames: int, batch_size: int = 16) -> np.ndarray:
    """IDM trajectories ``(N, 8, 3)`` of whole videos ``(N, T, H, W, 3)`` uint8."""
    dev = next(idm.parameters()).device
    out = []
    with torch.no_grad():
        for i in range(0, len(videos), batch_size):
            v = torch.from_numpy(np.ascontiguousarray(videos[i:i + batch_size])).permute(0, 1, 4, 2, 3)
            out.append(idm(idm.window(v, num_history_frames).to(dev)).cpu())
    return torch.cat(out).numpy()


def _l2(pred: np.ndarray, target: np.ndarray) -> dict:
    """Trajectory Difference: L2 (x, y) between trajectories, mean over waypoints and at the last one (m)."""
    e = trajectory_errors(pred, target)
    return {"trajectory_difference_m": e["ade_m"], "trajectory_difference_final_m": e["fde_m"],
            "yaw_difference_deg": e["yaw_err_deg"], "n": e["n"]}


def _end(traj: np.ndarray) -> list[float]:
    """The last waypoint's (x forward, y left) in metres, rounded for the report."""
    return [round(float(traj[-1, 0]), 2), round(float(traj[-1, 1]), 2)]


def end_point_slopes(read: np.ndarray, given: np.ndarray) -> dict:
    """How far the trajectory read off the videos moves with the one they were given, per axis of the last
    waypoint: the least-squares slope of read on given over the videos (1: followed one for one; 0: the read
    does not change with the given one). ``read``/``given`` ``(N, K, 3)``. Trajectory Difference mixes speed and
    steering; these two numbers tell them apart ("forward" is mostly speed, "lateral" mostly the turn)."""
    out: dict[str, Any] = {"n": int(len(read))}
    for name, ax in (("forward", 0), ("lateral", 1)):
        g, r = given[:, -1, ax].astype(np.float64), read[:, -1, ax].astype(np.float64)
        var = float(np.var(g))
        out[f"{name}_slope"] = float(np.mean((g - g.mean()) * (r - r.mean())) / var) if var > 1e-9 else None
    return out


def flow_labeler_status() -> tuple[Any, str]:
    """(FlowLabeler instance or None, reason). The labeler is part of this tree, so always the default one and
    no reason; callers keep the pair form to say why a metric is missing."""
    return FlowLabeler(labeler_preset("default")), ""


def command_accuracy(videos: np.ndarray, commands: Sequence[str | None], num_history_frames: int, fps_hz: float,
                     labeler: Any) -> dict:
    """Share of generated futures whose flow-labelled command equals the conditioning command."""
    got = []
    for v, c in zip(videos, commands):
        if c is None:
            continue
        lab = labeler.label(list(v[num_history_frames - 1:]), fps_hz)
        got.append((lab.command, c))
    n = len(got)
    return {"accuracy": (sum(a == b for a, b in got) / n) if n else None, "n": n,
            "confusion": [{"conditioned": b, "labelled": a} for a, b in got]}


def _other_clip_index(clips: Sequence[EvalClip], i: int, seed: int) -> int:
    """A clip of another episode, chosen by a seeded hash (deterministic, independent of list order)."""
    cands = [j for j, c in enumerate(clips) if c.item_id != clips[i].item_id and c.trajectory is not None]
    if not cands:
        eps = sorted({c.item_id for c in clips})
        raise ValueError(f"non-expert trajectories come from another episode, but the {len(clips)} clip(s) "
                         f"evaluated are all of episode {eps[0]!r}: evaluate more clips (a larger --limit, "
                         "--all-clips, or a split holding out more: `resim shards split DIR --min-heldout-episodes 2`)")
    return min(cands, key=lambda j: hashlib.sha256(f"{seed}\0{clips[i].key}\0{clips[j].key}".encode()).hexdigest())


def non_expert_pairs(clips: Sequence[EvalClip], seed: int = 0) -> list[int]:
    """For each clip with a trajectory (in order), the index (among those clips) of the clip whose trajectory
    and command condition its non-expert rollout. ValueError when they all come from one episode: called
    before any rollout so that the mistake costs nothing."""
    clips = [c for c in clips if c.trajectory is not None]
    if not clips:
        raise ValueError("no held-out clips with a trajectory")
    return [_other_clip_index(clips, i, seed) for i in range(len(clips))]


def idm_fits(*idms: Any) -> Callable[[EvalClip], bool]:
    """Whether each of ``idms`` (an IDM, the VO planner) can read a clip: its frame window fits the clip's
    history and length (a dataset may mix 10-Hz clips with 2-Hz NAVSIM ones)."""
    def fits(c: EvalClip) -> bool:
        try:
            for m in idms:
                m.cfg.frame_indices(c.num_history_frames, len(c.frames))
        except ValueError:
            return False
        return True
    return fits


def check_idm_window(idm: Any, clips: Sequence[EvalClip], what: str = "IDM") -> None:
    """ValueError if ``idm``'s frame window does not fit the clips' geometry (history frames, length).

    The IDM runs on videos as long as the clips (history + generated future); checked before the rollouts,
    which are the expensive part, instead of failing after all of them."""
    seen = set()
    for c in clips:
        geo = (c.num_history_frames, len(c.frames))
        if geo in seen:
            continue
        seen.add(geo)
        try:
            idm.cfg.frame_indices(*geo)
        except ValueError as e:
            raise ValueError(f"{what} ({idm.cfg.window} window, {idm.cfg.num_frames} frames every "
                             f"{idm.cfg.frame_step}) does not fit clip {c.key}: {e}") from None


def trajectory_bounds(rep: dict) -> dict:
    """The synthetic world's trajectory targets (docs/models/synth-world.md) on a :func:`control_eval` report: the
    expert Trajectory Difference (1) at most 1.5x the IDM's own error on the recorded video, and (2) below half the
    distance of the same rollouts to a trajectory they were not given (another episode's). A model that ignored its
    trajectory would read (2) near 1; ``recorded_video_over_not_given`` is (2) for the recorded video itself, what a
    model that predicted the recorded future exactly would read through this IDM."""
    td = lambda k: rep[k]["trajectory_difference_m"]  # noqa: E731

    def ratio(a: float, b: float) -> float:     # 0 / 0: nothing to tell apart, read as met
        return a / b if b > 0 else (0.0 if a == 0 else float("inf"))

    r1 = ratio(td("expert"), td("idm_on_recorded_video"))
    r2 = ratio(td("expert"), td("expert_vs_not_given"))
    return {"expert_over_idm_floor": r1, "expert_over_idm_floor_max": 1.5, "expert_over_idm_floor_met": bool(r1 <= 1.5),
            "expert_over_not_given": r2, "expert_over_not_given_max": 0.5, "expert_over_not_given_met": bool(r2 < 0.5),
            "recorded_video_over_not_given": ratio(td("idm_on_recorded_video"), td("recorded_video_vs_not_given"))}


def control_eval(runner: WorldRollouts, idm: Any, clips: Sequence[EvalClip], seed: int = 0) -> dict:
    clips = [c for c in clips if c.trajectory is not None]
    if not clips:
        raise ValueError("no held-out clips with a trajectory")
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    check_idm_window(idm, clips)
    expert_t = [c.trajectory for c in clips]
    expert_c = [c.command for c in clips]
    others = non_expert_pairs(clips, seed)
    non_t = [clips[j].trajectory for j in others]
    non_c = [clips[j].command for j in others]
    vid_e = runner.generate(clips, expert_t, expert_c)
    vid_n = runner.generate(clips, non_t, non_c)
    pred_e, pred_n = _idm_on(idm, vid_e, nh), _idm_on(idm, vid_n, nh)
    gt_vid = np.stack([c.frames for c in clips])
    pred_gt = _idm_on(idm, gt_vid, nh)
    # the recorded latents decoded as a rollout is: what a model that predicted the recorded future exactly would
    # score. The rollouts reach the IDM through the VAE; this floor tells the VAE's share of their error apart
    # from the model's (the labeler's "recorded through the VAE" in commands.py is the same idea)
    pred_vae = _idm_on(idm, runner.decode_recorded(clips), nh)
    rep: dict[str, Any] = {
        "expert": _l2(pred_e, np.stack(expert_t)),
        "non_expert": _l2(pred_n, np.stack(non_t)),
        "idm_on_recorded_video": _l2(pred_gt, np.stack(expert_t)),
        "idm_on_recorded_through_vae": _l2(pred_vae, np.stack(expert_t)),
        # the expert rollouts against a trajectory they were not given (the other episode's): a model that ignored
        # its trajectory would read the expert row about this far. The recorded video against it: the same control
        # for a model that is exactly right
        "expert_vs_not_given": _l2(pred_e, np.stack(non_t)),
        "recorded_video_vs_not_given": _l2(pred_gt, np.stack(non_t)),
        "non_expert_vs_recorded_trajectory_m": _l2(np.stack(non_t), np.stack(expert_t))["trajectory_difference_m"],
        "followed": {"rollouts": end_point_slopes(np.concatenate([pred_e, pred_n]),
                                                  np.concatenate([np.stack(expert_t), np.stack(non_t)])),
                     "idm_on_recorded_video": end_point_slopes(pred_gt, np.stack(expert_t)),
                     "idm_on_recorded_through_vae": end_point_slopes(pred_vae, np.stack(expert_t))},
        "pairs": [{"clip": c.key, "non_expert_from": clips[j].key,
                   "end_m": {"expert": _end(expert_t[i]), "expert_read": _end(pred_e[i]),
                             "non_expert": _end(non_t[i]), "non_expert_read": _end(pred_n[i]),
                             "recorded_read": _end(pred_gt[i])}}
                  for i, (c, j) in enumerate(zip(clips, others))],
    }
    rep["bounds"] = trajectory_bounds(rep)
    labeler, reason = flow_labeler_status()
    if labeler is None:
        rep["command_accuracy"] = f"not available: {reason}"
    else:
        rep["command_accuracy"] = {"expert": command_accuracy(vid_e, expert_c, nh, fps, labeler),
                                   "non_expert": command_accuracy(vid_n, non_c, nh, fps, labeler),
                                   "recorded_video": command_accuracy(gt_vid, expert_c, nh, fps, labeler)}
    rep["_videos"] = {"expert": vid_e, "non_expert": vid_n}
    return rep


@dataclass
class PlanningEvalConfig:
    """`resim eval planning`'s settings beyond its flags (``--set planning.KEY=VALUE``)."""
    with_command: bool = False   # give the video-prediction policy the clip's command prompt (default: none)


def planning_eval(runner: WorldRollouts, idm: Any, planner: Any | None, clips: Sequence[EvalClip],
                  with_command: bool = False) -> dict:
    clips = [c for c in clips if c.trajectory is not None]
    if not clips:
        raise ValueError("no held-out clips with a trajectory")
    nh = clips[0].num_history_frames
    check_idm_window(idm, clips)
    if planner is not None:  # checked before the rollouts, like the IDM's window
        if planner.cfg.window != "history":
            raise ValueError("the VO-style planner must see history frames only (window='history')")
        check_idm_window(planner, clips, "VO planner")
    gt = np.stack([c.trajectory for c in clips])
    vids = runner.generate(clips, [None] * len(clips), [c.command if with_command else None for c in clips])
    rep: dict[str, Any] = {"video_prediction_policy": trajectory_errors(_idm_on(idm, vids, nh), gt),
                           "constant_velocity": trajectory_errors(constant_velocity(gt), gt),
                           "idm_on_recorded_future": trajectory_errors(
                               _idm_on(idm, np.stack([c.frames for c in clips]), nh), gt)}
    if planner is not None:
        rep["vo_planner_history_only"] = trajectory_errors(
            _idm_on(planner, np.stack([c.frames for c in clips]), nh), gt)
    else:
        rep["vo_planner_history_only"] = "not available: no planner checkpoint given"
    rep["_videos"] = {"policy": vids}
    return rep


def quality_eval(runner: WorldRollouts, clips: Sequence[EvalClip], qcfg: Any, networks: Any = None) -> dict:
    ev = VideoQualityEvaluator(qcfg, networks)
    for i in range(0, len(clips), runner.batch_size):
        part = clips[i:i + runner.batch_size]
        # offset=i: the seeds one generate() call on all clips would use (each batch its own noise)
        gen = runner.generate(part, [c.trajectory for c in part], [c.command for c in part], offset=i)
        gt = np.stack([c.frames for c in part])
        g = torch.from_numpy(gen).permute(0, 1, 4, 2, 3)
        r = torch.from_numpy(gt).permute(0, 1, 4, 2, 3)
        if g.shape[1] != r.shape[1]:
            raise ValueError(f"generated {g.shape[1]} frames, the clip has {r.shape[1]}")
        if g.shape[-2:] != r.shape[-2:]:   # VAE resolution vs frames.mp4: bring generated to the GT's size

            g = torch.from_numpy(np.stack([resize_frames(v, tuple(r.shape[-2:])) for v in gen])).permute(0, 1, 4, 2, 3)
        ev.update(g, r)
    rep = ev.compute()
    rep["protocol"]["generated_resize"] = ("generated frames resized from the VAE's resolution "
                                           f"{tuple(gen.shape[2:4])} to the recorded frames' {tuple(gt.shape[2:4])} "
                                           "(bilinear, antialias) before scoring"
                                           if tuple(gen.shape[2:4]) != tuple(gt.shape[2:4]) else "none")
    return rep
