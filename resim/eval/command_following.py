"""Command controllability on held-out clips: does the world model turn where it is told to?

ReSim's headline is controllability; the complaint of world-model users is "the command doesn't change
anything". The protocol (counterfactual commands from one history):

* every held-out clip's history is rolled out once under **each** of the three commands (no trajectory), so a
  history recorded on a straight road is also asked to turn left and right (counterfactual commands);
* each generated future (the last history frame + the generated frames) is classified by the optical-flow
  labeler (``resim.labeling.flow.FlowLabeler``, the one that labels real video), and, when an inverse dynamics
  model is given, by ``command_from_trajectory`` of the IDM's trajectory;
* controls beside it: the **null prompt** (prefix only: the model is not told where to go; its futures are
  scored against each of the three commands, so a model that ignores the command scores 1/3 whatever it
  draws), and the **recorded future** (the labeler on the real frames against the recorded command: the
  labeler's own ceiling), and the **recorded future through the VAE** (the clip's own latents decoded as a
  rollout is: what a world model that predicted the recorded future exactly would score; a VAE that smears
  the ego motion caps every model's accuracy here);
* **fidelity per horizon** of the rollouts under the recorded command against the recorded future, beside
  the copy-last-frame baseline (the last history frame held).
* **counterfactual branches**, where the clips hold forks (one history recorded under several commands): each
  rollout is scored by the recorded sibling future it lands on, in latent space (``resim.eval.branches``), a
  reading of the model that the VAE and the labeler do not cap.
* **trajectory branches** (``trajectory_branches=True``), on the forks whose clips carry their recorded
  trajectory: each history is rolled out with the null prompt under each sibling's recorded trajectory and
  scored the same way. The trajectory is then the only thing that tells the branches apart, so this reads
  ReSim's trajectory conditioning without the IDM, whose error on this world is close to constant velocity's.
* **the group-end reading** (``group_ends=True``), a diagnostic: the labeler on the same videos with the frames
  inside each latent group redrawn from the group ends (``resim.eval.group_frames``). A decoder that cross-fades
  between group ends hides a turn from the labeler; this reading shows what the latents turn without it.

The rollouts are done by :class:`resim.eval.worldeval.WorldRollouts`, so they use the sampler users use.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from resim.config import ConfigError
from resim.eval.branches import (branch_matching, counterfactual_groups, sibling_trajectory_requests,
                                    trajectory_groups)
from resim.eval.fidelity import psnr, ssim
from resim.eval.group_frames import redraw_all
from resim.eval.worldeval import EvalClip, WorldRollouts, _idm_on
from resim.labeling.commands import command_from_trajectory
from resim.labeling.config import preset as labeler_preset
from resim.shards.schema import COMMANDS

NULL = "null prompt"


def confusion(conditioned: Sequence[str], labelled: Sequence[str]) -> dict:
    """3x3 counts ``matrix[i][j]`` = rollouts conditioned on ``COMMANDS[i]`` labelled ``COMMANDS[j]``; accuracy."""
    m = np.zeros((3, 3), dtype=int)
    for c, lab in zip(conditioned, labelled):
        m[COMMANDS.index(c), COMMANDS.index(lab)] += 1
    n = int(m.sum())
    return {"commands": list(COMMANDS), "matrix": m.tolist(), "n": n,
            "accuracy": float(np.trace(m) / n) if n else None,
            "per_command": {c: (float(m[i, i] / m[i].sum()) if m[i].sum() else None) for i, c in enumerate(COMMANDS)}}


def flow_commands(videos: np.ndarray, num_history_frames: int, fps_hz: float, labeler: Any) -> tuple[list[str], list[float]]:
    """The labeler's command and heading change (deg, left +) for each video's future
    (from the last history frame on)."""
    cmds, yaws = [], []
    for v in videos:
        lab = labeler.label(list(v[num_history_frames - 1:]), fps_hz)
        cmds.append(lab.command)
        yaws.append(float(lab.yaw_deg))
    return cmds, yaws


def flow_rates(videos: np.ndarray, num_history_frames: int, fps_hz: float,
               labeler: Any) -> tuple[list[str], list[float], list[np.ndarray]]:
    """:func:`flow_commands` and, per video, the yaw rate of each frame pair of its future that the label summed
    (deg/s, left +; pair ``j`` ends on frame ``num_history_frames + j``; ``FlowLabeler.last_rates_deg_s``)."""
    cmds, yaws, rates = [], [], []
    for v in videos:
        lab = labeler.label(list(v[num_history_frames - 1:]), fps_hz)
        cmds.append(lab.command)
        yaws.append(float(lab.yaw_deg))
        rates.append(np.asarray(labeler.last_rates_deg_s, np.float64))
    return cmds, yaws, rates


def labeler_lean(videos: np.ndarray, yaws: Sequence[float], num_history_frames: int, fps_hz: float,
                 labeler: Any) -> float:
    """The labeler's own left-right asymmetry on ``videos`` (``(N, T, H, W, 3)`` uint8), deg: the mean over the
    videos of (heading ``yaws`` + heading of the video mirrored left-right) / 2. An unbiased reading flips sign
    under the mirror, so this is ~0 and a mean heading away from 0 is the videos' own."""
    mirrored = np.ascontiguousarray(videos[:, :, :, ::-1])
    return float(np.mean(np.add(yaws, flow_commands(mirrored, num_history_frames, fps_hz, labeler)[1])) / 2)


def idm_commands(videos: np.ndarray, num_history_frames: int, idm: Any, labeler_cfg: Any) -> list[str]:
    return [command_from_trajectory(t, labeler_cfg)[0] for t in _idm_on(idm, videos, num_history_frames)]


def fidelity_per_horizon(gen: np.ndarray, ref: np.ndarray, num_history_frames: int, fps_hz: float,
                         horizons_s: Sequence[float]) -> dict:
    """PSNR/SSIM of the frame ``h`` seconds after the last history frame, for generated videos and for the
    copy-last-frame baseline; ``gen``/``ref`` uint8 ``(N, T, H, W, 3)`` of one size."""
    g = torch.from_numpy(np.ascontiguousarray(gen)).permute(0, 1, 4, 2, 3)
    r = torch.from_numpy(np.ascontiguousarray(ref)).permute(0, 1, 4, 2, 3)
    last = r[:, num_history_frames - 1:num_history_frames].expand_as(r)
    rows = []
    for h in horizons_s:
        f = num_history_frames - 1 + int(round(h * fps_hz))
        if f >= r.shape[1]:
            continue
        sl = slice(f, f + 1)
        row = {"horizon_s": float(h), "frame": int(f)}
        for name, video in (("model", g), ("copy_last_frame", last)):
            row[f"psnr_{name}"] = float(psnr(video[:, sl], r[:, sl], "uint8").mean())
            row[f"ssim_{name}"] = float(ssim(video[:, sl], r[:, sl], "uint8").mean())
        rows.append(row)
    return {"per_horizon": rows, "clips": int(len(gen))}


@dataclass
class CommandsEvalConfig:
    """`resim eval commands`' settings beyond its flags (``--set commands.KEY=VALUE``)."""
    horizons_s: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)   # fidelity horizons after the last history frame
    trajectory_branches: bool = False   # also roll the forks out under their siblings' recorded trajectories
    group_ends: bool = False            # diagnostic: also read each video redrawn between its latent group ends

    def __post_init__(self) -> None:
        if not self.horizons_s or any(not h > 0 for h in self.horizons_s):
            raise ConfigError(f"horizons_s={list(self.horizons_s)}: give one or more horizons > 0 s")


def commands_eval(runner: WorldRollouts, clips: Sequence[EvalClip], labeler: Any, *, idm: Any = None,
                  horizons_s: Sequence[float] = (0.5, 1.0, 2.0, 4.0), trajectory_branches: bool = False,
                  group_ends: bool = False) -> dict:
    """The protocol above on ``clips`` (one geometry); returns the report (``_videos`` holds the rollouts).
    ``trajectory_branches``: also roll the forks out under their siblings' trajectories (report key
    ``trajectory_branches``). ``group_ends``: also the diagnostic reading of :func:`group_end_reading` (report key
    ``flow_labeler_group_ends``)."""
    if not clips:
        raise ValueError("no clips to evaluate")
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    n = len(clips)
    videos: dict[str, np.ndarray] = {}
    futures: dict[str, np.ndarray] = {}
    h = runner.history_latents(clips[0])
    for c in (*COMMANDS, None):
        lat = runner.generate_latents(clips, [None] * n, [c] * n)
        futures[c or NULL] = lat[:, h:].numpy()
        videos[c or NULL] = runner.decode(clips, lat)
    gt = np.stack([c.frames for c in clips])
    if gt.shape[2:4] != videos[COMMANDS[0]].shape[2:4]:
        raise ValueError(f"recorded frames {gt.shape[2:4]} and decoded rollouts {videos[COMMANDS[0]].shape[2:4]} "
                         "differ in size: encode the evaluation shards with frames at the VAE's resolution")

    flow = {k: flow_commands(v, nh, fps, labeler) for k, v in videos.items()}
    gt_flow, gt_yaw = flow_commands(gt, nh, fps, labeler)
    through_vae = runner.decode_recorded(clips)
    vae_flow, vae_yaw = flow_commands(through_vae, nh, fps, labeler)
    recorded = [c.command for c in clips]
    rep: dict[str, Any] = {"flow_labeler": {}, "idm": {}}
    cond = [c for c in COMMANDS for _ in range(n)]
    rep["flow_labeler"]["commanded"] = confusion(cond, [lab for c in COMMANDS for lab in flow[c][0]])
    rep["flow_labeler"]["null_prompt"] = confusion(cond, [lab for _ in COMMANDS for lab in flow[NULL][0]])
    rep["flow_labeler"]["null_prompt_vs_recorded"] = confusion(recorded, flow[NULL][0])
    rep["flow_labeler"]["recorded_future"] = confusion(recorded, gt_flow)
    rep["flow_labeler"]["mean_yaw_deg"] = {k: float(np.mean(v[1])) for k, v in flow.items()}
    rep["flow_labeler"]["recorded_through_vae"] = confusion(recorded, vae_flow)
    rep["flow_labeler"]["mean_yaw_deg"]["recorded future"] = float(np.mean(gt_yaw))
    rep["flow_labeler"]["mean_yaw_deg"]["recorded through the VAE"] = float(np.mean(vae_yaw))
    # the labeler on the same videos mirrored left-right: an unbiased reading flips sign, so the mean of the two is
    # the labeler's own left-right asymmetry on these videos. Near 0, a lean in mean_yaw_deg is the videos'
    rep["flow_labeler"]["mirror_check_deg"] = {k: labeler_lean(v, flow[k][1], nh, fps, labeler)
                                               for k, v in videos.items()}
    rep["flow_labeler"]["mirror_check_deg"]["recorded future"] = labeler_lean(gt, gt_yaw, nh, fps, labeler)
    if group_ends:
        tc = clips[0].temporal_compression
        rep["flow_labeler_group_ends"] = (group_end_reading(
            {k: v for k, v in videos.items() if k != NULL}, gt, through_vae, recorded, nh, fps, labeler, tc)
            if tc > 1 else {"skipped": "a per-frame VAE (temporal ratio 1) has no frames inside a latent group"})
    if idm is not None:
        lcfg = labeler_preset("default")
        by_idm = {k: idm_commands(v, nh, idm, lcfg) for k, v in videos.items()}
        rep["idm"]["commanded"] = confusion(cond, [lab for c in COMMANDS for lab in by_idm[c]])
        rep["idm"]["null_prompt"] = confusion(cond, [lab for _ in COMMANDS for lab in by_idm[NULL]])
        rep["idm"]["recorded_future"] = confusion(recorded, idm_commands(gt, nh, idm, lcfg))
    else:
        rep["idm"] = "not run: no --idm given"

    # fidelity: the rollout under each clip's recorded command (no trajectory) against the recorded future
    under_recorded = np.stack([videos[c.command][i] if c.command in COMMANDS else videos[NULL][i]
                               for i, c in enumerate(clips)])
    rep["fidelity"] = fidelity_per_horizon(under_recorded, gt, nh, fps, horizons_s)
    # forks: the same history recorded under different commands; where the clips have them, score each rollout by
    # the recorded sibling future it lands on (resim/eval/branches.py: not capped by the VAE or the labeler)
    groups = counterfactual_groups(clips)
    rep["branches"] = (branch_matching(futures, np.stack([c.latents[h:] for c in clips]), recorded, groups,
                                       null_key=NULL) if groups else
                       {"skipped": "no counterfactual clips (no two clips share a history under different commands; "
                                   "resim synth --set fork_fraction=... makes them)"})
    if trajectory_branches:
        rep["trajectory_branches"] = (trajectory_branch_eval(runner, clips, groups, futures[NULL], h) if groups else
                                      {"skipped": "no counterfactual clips"})
    rep["clips"] = [{"key": c.key, "episode": c.item_id, "recorded_command": c.command,
                     "recorded_future_flow": gt_flow[i], "recorded_through_vae_flow": vae_flow[i],
                     **{f"flow_{k}": flow[k][0][i] for k in videos}} for i, c in enumerate(clips)]
    rep["_videos"] = {**videos, "recorded": gt}
    return rep


def group_end_reading(videos: dict[str, np.ndarray], recorded_video: np.ndarray, through_vae: np.ndarray,
                      recorded: Sequence[str | None], num_history_frames: int, fps_hz: float, labeler: Any,
                      group: int = 4) -> dict:
    """The flow labeler on the videos with the frames inside each latent group redrawn from the group ends
    (resim/eval/group_frames.py): what the rollouts' latents turn, without the decoder's cross-fade between
    group ends. A diagnostic beside the labeler on the decoded frames, which stays the measure. ``videos``: command
    → uint8 ``(N, T, H, W, 3)`` rollouts under it; the recorded future (originals, the reading's own ceiling) and
    the recorded future through the VAE are redrawn and read alike."""
    flow = {k: flow_commands(redraw_all(v, group), num_history_frames, fps_hz, labeler) for k, v in videos.items()}
    gt_c, gt_y = flow_commands(redraw_all(recorded_video, group), num_history_frames, fps_hz, labeler)
    vae_c, vae_y = flow_commands(redraw_all(through_vae, group), num_history_frames, fps_hz, labeler)
    cond = [c for c in videos for _ in range(len(recorded_video))]
    mean = {k: float(np.mean(v[1])) for k, v in flow.items()}
    return {"commanded": confusion(cond, [lab for c in videos for lab in flow[c][0]]),
            "recorded_future": confusion(list(recorded), gt_c),
            "recorded_through_vae": confusion(list(recorded), vae_c),
            "mean_yaw_deg": {**mean, "recorded future": float(np.mean(gt_y)),
                             "recorded through the VAE": float(np.mean(vae_y))},
            "what": f"frames inside each {group}-frame latent group redrawn by optical-flow interpolation between "
                    "the group ends, then read by the flow labeler: a diagnostic, not the target's measure"}


def trajectory_branch_eval(runner: WorldRollouts, clips: Sequence[EvalClip], groups: Sequence[Sequence[int]],
                           null_futures: np.ndarray, h: int) -> dict:
    """Counterfactual branches under the siblings' recorded trajectories, the command withheld (null prompt).

    ``null_futures``: ``(N, F, C, h, w)`` the null-prompt rollouts of all ``clips`` (no trajectory): the control,
    scored against the same forks. ``h``: history latent frames. Returns :func:`branch_matching`'s report on the
    forks whose every clip carries a trajectory, or ``{"skipped": reason}``."""
    tgroups = trajectory_groups(clips, groups)
    if not tgroups:
        return {"skipped": "no fork whose every clip carries its recorded trajectory (the CARLA layout records them)"}
    sub = sorted(i for g in tgroups for i in g)
    pos = {i: k for k, i in enumerate(sub)}
    reqs = sibling_trajectory_requests(clips, tgroups)
    fut = runner.generate_latents([clips[i] for i, _, _ in reqs], [t for _, _, t in reqs],
                                  [None] * len(reqs))[:, h:].numpy()
    # only the commands a fork recorded are asked (and read) by branch_matching; the rest stay NaN
    gen = {c: np.full((len(sub),) + fut.shape[1:], np.nan, np.float32) for c in COMMANDS}
    for k, (i, c, _) in enumerate(reqs):
        gen[c][pos[i]] = fut[k]
    gen[NULL] = null_futures[sub]
    rep = branch_matching(gen, np.stack([clips[i].latents[h:] for i in sub]), [clips[i].command for i in sub],
                          [[pos[i] for i in g] for g in tgroups], null_key=NULL)
    rep["given"] = "the null prompt and the recorded trajectory of the sibling recorded under each command"
    rep["clips"] = len(sub)
    return rep


def balanced_clips(clips: Sequence[EvalClip], limit: int) -> list[EvalClip]:
    """At most ``limit`` clips, taking the recorded commands in turn (left, forward, right) and, within a
    command, the episodes in turn: histories on straight roads are as common as histories in curves, so the
    counterfactual turns are asked of both."""
    by_cmd: dict[str, dict[str, list[EvalClip]]] = {}
    for c in sorted(clips, key=lambda c: c.key):
        by_cmd.setdefault(c.command or "", {}).setdefault(c.item_id, []).append(c)
    queues = [[q for q in by_ep.values()] for _, by_ep in sorted(by_cmd.items())]
    picked: list[EvalClip] = []
    while len(picked) < limit and any(any(q) for q in queues):
        for eps in queues:
            for q in eps:
                if q:
                    picked.append(q.pop(0))
                    eps.append(eps.pop(eps.index(q)))   # next time, the next episode of this command
                    break
            if len(picked) >= limit:
                break
    return sorted(picked, key=lambda c: c.key)
