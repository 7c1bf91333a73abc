"""Reconstruction quality of a VAE on held-out clips (``resim eval vae``): PSNR / SSIM per frame of the clip,
and a picture of originals beside reconstructions.

Each clip's recorded frames (``frames.mp4``, at the resolution the pipeline encoded) go through the VAE as the
pipeline runs it (``resim.media.encoders.VideoVAE.encode``: one posterior sample x scaling factor) and back
through the sampler's decode (``resim.sample.outputs.decode_latents``), i.e. exactly the round trip a
world-model rollout's frames take. Frame ``k``'s metrics average over clips, so the causal VAE's first
frame (encoded alone) and the frames at its 4-frame chunk boundaries show up separately.

**Motion through the VAE.** PSNR does not say whether the ego motion survives the round trip, and the
controllability metric (``resim eval commands``) reads it off decoded video with the optical-flow labeler.
Given the labeler, the evaluation also labels each clip's future on the originals and on the
reconstructions: the labeler's accuracy on reconstructions is the ceiling of any world model's command
accuracy through this VAE (a blur of the same PSNR keeps the heading; a VAE that smears the motion does not).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from resim.eval.command_following import confusion, flow_commands, flow_rates
from resim.eval.fidelity import psnr, ssim
from resim.eval.group_frames import redraw_all
from resim.eval.heading_kept import paired_mean_difference, paired_slope_difference, slope
from resim.sample.outputs import decode_latents


TURNING_DEG = 10.0   # the heading change (deg) over a clip's future that counts it as turning for the heading kept
GROUP_FRAMES = 4     # frames per latent group of the 4x temporal VAE: frame 0 alone, then frames 1-4, 5-8, ...


def heading_kept_by_group_place(orig_rates: Sequence[np.ndarray], rec_rates: Sequence[np.ndarray],
                                num_history_frames: int, turning: np.ndarray,
                                group: int = GROUP_FRAMES) -> list[Optional[float]]:
    """Where inside a latent group a VAE loses the heading: for each place ``k`` of a frame in its group (0: the
    group's first frame, so the pair reaching it crosses from the previous group's end; ``group - 1``: the group's
    end), the heading kept over the frame pairs that end on such frames, i.e. the slope of the reconstructions'
    summed yaw over those pairs on the originals' (:func:`resim.eval.heading_kept.slope`), over the ``turning``
    clips (a boolean mask). Per-pair rates as :func:`resim.eval.command_following.flow_rates` gives them: pair ``j`` ends
    on frame ``num_history_frames + j``. A decoder that draws a group as a cross-fade between its ends keeps little
    at every place; one that holds a frame and then jumps keeps it all at place 0 and none at the others."""
    if len(orig_rates) != len(rec_rates) or len(orig_rates) != len(turning):
        raise ValueError(f"{len(orig_rates)} original, {len(rec_rates)} reconstructed clips and {len(turning)} "
                         "turning flags: one of each per clip is needed")
    idx = np.flatnonzero(turning)
    if not idx.size:
        return [None] * group

    def by_place(rates: Sequence[np.ndarray]) -> np.ndarray:           # (clips, group): summed rate per place
        return np.array([np.bincount((num_history_frames + np.arange(len(r)) - 1) % group, weights=r, minlength=group)
                         for r in rates])

    o, c = by_place(orig_rates), by_place(rec_rates)
    return [slope(c[:, k], o[:, k], idx) for k in range(group)]


def reconstruct(vae: Any, frames: np.ndarray, seeds: Sequence[int]) -> np.ndarray:
    """uint8 ``(B, T, H, W, 3)`` → the VAE's reconstruction, same shape and dtype."""
    lat = vae.encode(frames, seeds=list(seeds))
    return decode_latents(vae, torch.from_numpy(lat), batch_size=len(lat))


def motion_through(labeler: Any, frames: Sequence[np.ndarray], recs: Sequence[np.ndarray],
                   clips: Sequence[Any], group_ends: bool = False, group: int = GROUP_FRAMES) -> dict:
    """The flow labeler's command and heading change (deg, left +) of each clip's future, on the originals
    and on the reconstructions; accuracies against the recorded commands, and how much heading survives.
    ``group_ends``: also the same reading with the frames inside each latent group redrawn from the group ends
    (resim/eval/group_frames.py, a diagnostic: how much of the loss is the decoder's drawing inside a group),
    on the reconstructions and, for the reading's own ceiling, on the originals. ``group``: the VAE's temporal
    ratio, the frames per latent group (1: a per-frame VAE, which has no inside of a group to redraw)."""
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    raw_c, raw_y, raw_r = flow_rates(np.stack(frames), nh, fps, labeler)
    rec_c, rec_y, rec_r = flow_rates(np.stack(recs), nh, fps, labeler)
    recorded = [c.command for c in clips]
    keep = [i for i, c in enumerate(recorded) if c is not None]
    ry, cy = np.asarray(raw_y), np.asarray(rec_y)
    turning = np.abs(ry) >= TURNING_DEG
    out = {"labeler_on_originals": confusion([recorded[i] for i in keep], [raw_c[i] for i in keep]),
            "labeler_on_reconstructions": confusion([recorded[i] for i in keep], [rec_c[i] for i in keep]),
            "same_label": float(np.mean([a == b for a, b in zip(raw_c, rec_c)])),
            "heading_kept": slope(cy, ry, np.flatnonzero(turning)) if turning.any() else None,
            # 0: frames starting a latent group (the pair from the previous group's end) ... 3: the group's end
            "heading_kept_by_group_place": heading_kept_by_group_place(raw_r, rec_r, nh, turning, group),
            "mean_abs_heading_deg": {"originals": float(np.abs(ry).mean()), "reconstructions": float(np.abs(cy).mean())},
            "clips": len(clips), "turning_clips": int(turning.sum()),
            # per clip, for paired comparisons of two VAEs on the same clips (--against)
            "per_clip": {"recorded": recorded, "originals_command": list(raw_c), "reconstructions_command": list(rec_c),
                         "originals_yaw_deg": ry.tolist(), "reconstructions_yaw_deg": cy.tolist()}}
    if group_ends and group > 1:
        g_raw_c, g_raw_y = flow_commands(redraw_all(np.stack(frames), group), nh, fps, labeler)
        g_rec_c, g_rec_y = flow_commands(redraw_all(np.stack(recs), group), nh, fps, labeler)
        idx = np.flatnonzero(turning)
        out["group_ends"] = {
            "labeler_on_originals": confusion([recorded[i] for i in keep], [g_raw_c[i] for i in keep]),
            "labeler_on_reconstructions": confusion([recorded[i] for i in keep], [g_rec_c[i] for i in keep]),
            "heading_kept": slope(np.asarray(g_rec_y), ry, idx) if turning.any() else None,
            "originals_heading_kept": slope(np.asarray(g_raw_y), ry, idx) if turning.any() else None,
            "what": f"frames inside each {group}-frame latent group redrawn by optical-flow interpolation between the "
                    "group ends; heading kept against the originals as they are"}
    return out


def vae_eval(vae: Any, clips: Sequence[Any], batch_size: int = 2, labeler: Any = None,
             group_ends: bool = False) -> dict:
    """Per-frame PSNR/SSIM over ``clips`` (``EvalClip``: ``.frames`` uint8 (T, H, W, 3)); ``_examples`` holds
    the first batch's originals and reconstructions for the picture. With ``labeler`` (``FlowLabeler``),
    ``motion`` (:func:`motion_through`, with ``group_ends``): does the ego motion survive the round trip?"""
    per_psnr, per_ssim, examples = [], [], None
    all_frames, all_recs = [], []
    for i in range(0, len(clips), batch_size):
        part = clips[i:i + batch_size]
        frames = np.stack([c.frames for c in part])
        rec = reconstruct(vae, frames, seeds=range(i, i + len(part)))
        g = torch.from_numpy(rec).permute(0, 1, 4, 2, 3)
        r = torch.from_numpy(frames).permute(0, 1, 4, 2, 3)
        per_psnr.append(psnr(g, r, "uint8"))
        per_ssim.append(ssim(g, r, "uint8"))
        if examples is None:
            examples = (frames, rec)
        if labeler is not None:
            all_frames.extend(frames)
            all_recs.extend(rec)
    p, s = torch.cat(per_psnr), torch.cat(per_ssim)                  # (N, T)
    rep = {"psnr_db": {"mean": float(p.mean()), "per_clip_min": float(p.mean(1).min()),
                       "per_frame": p.mean(0).tolist(), "per_clip": p.mean(1).tolist()},
           "ssim": {"mean": float(s.mean()), "per_frame": s.mean(0).tolist()},
           "clips": len(clips), "frames_per_clip": int(p.shape[1]), "_examples": examples}
    if labeler is not None:
        rep["motion"] = motion_through(labeler, all_frames, all_recs, clips, group_ends=group_ends,
                                       group=int(vae.info.temporal_compression))
    return rep


def paired_vae_difference(rep: dict, other: dict, n_boot: int = 2000, seed: int = 0) -> dict:
    """This VAE's report minus ``other``'s, read on the same clips: PSNR (mean dB per clip), and, with the
    motion, the labeler's accuracy on the reconstructions and the heading kept on the turning clips, each with a
    95 % paired bootstrap interval over clips. Raises ``ValueError`` when the reports were not read on the same
    clips (their originals read differently) or one lacks the per-clip values (a report of an older resim)."""
    try:
        mine, theirs = np.asarray(rep["psnr_db"]["per_clip"]), np.asarray(other["psnr_db"]["per_clip"])
    except KeyError:
        raise ValueError("a report has no per-clip PSNR: rerun resim eval vae for it") from None
    if mine.shape != theirs.shape:
        raise ValueError(f"the two reports were read on different clips ({len(mine)} against {len(theirs)})")
    out = {"psnr_db": paired_mean_difference(mine, theirs, n_boot, seed), "clips": len(mine)}
    m, o = rep.get("motion"), other.get("motion")
    if m and o:
        a, b = m.get("per_clip"), o.get("per_clip")
        if a is None or b is None:
            raise ValueError("a report has no per-clip motion: rerun resim eval vae for it")
        ref = np.asarray(a["originals_yaw_deg"])
        if a["recorded"] != b["recorded"] or not np.allclose(ref, b["originals_yaw_deg"]):
            raise ValueError("the two reports were not read on the same clips (their originals read differently)")
        keep = [i for i, c in enumerate(a["recorded"]) if c is not None]
        right = lambda pc: [float(pc["reconstructions_command"][i] == pc["recorded"][i]) for i in keep]
        turning = np.abs(ref) >= TURNING_DEG
        out["labeler_on_reconstructions"] = paired_mean_difference(right(a), right(b), n_boot, seed)
        out["heading_kept"] = paired_slope_difference(np.asarray(a["reconstructions_yaw_deg"])[turning],
                                                      np.asarray(b["reconstructions_yaw_deg"])[turning], ref[turning],
                                                      n_boot, seed)
    return out


def format_vae_difference(diff: dict, other: str) -> str:
    """One line per measure of :func:`paired_vae_difference`."""
    names = {"psnr_db": ("PSNR", "dB"), "labeler_on_reconstructions": ("labeler accuracy through the VAE", ""),
             "heading_kept": ("heading kept", "")}
    lines = [f"against {other} (the same {diff['clips']} clips, paired bootstrap 95 %):"]
    for k, (name, unit) in names.items():
        if k in diff:
            d = diff[k]
            lines.append(f"  {name:34s} {d['difference']:+.3f}{unit} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}]")
    return "\n".join(lines)


def format_vae_eval(rep: dict) -> str:
    """The summary ``resim eval vae`` prints."""
    lines = [f"PSNR {rep['psnr_db']['mean']:.2f} dB (worst clip {rep['psnr_db']['per_clip_min']:.2f}), "
             f"SSIM {rep['ssim']['mean']:.3f} over {rep['clips']} clips"]
    m = rep.get("motion")
    if m:
        kept = "n/a (no turning clip)" if m["heading_kept"] is None else f"{m['heading_kept']:.2f}"
        lines.append(f"motion: flow-labeler accuracy on originals {m['labeler_on_originals']['accuracy']:.2f}, on "
                     f"reconstructions {m['labeler_on_reconstructions']['accuracy']:.2f} (the ceiling of a world "
                     f"model's command accuracy through this VAE); same label {m['same_label']:.2f}; heading kept "
                     f"{kept} on {m['turning_clips']} turning clips (1 = all)")
        places = m.get("heading_kept_by_group_place")
        if places and places[0] is not None:
            lines.append(f"heading kept by the frame's place in its {len(places)}-frame latent group (first ... "
                         "group end): " + " / ".join(f"{p:.2f}" for p in places))
        g = m.get("group_ends")
        if g:
            f = lambda x: "n/a" if x is None else f"{x:.2f}"
            lines.append(f"group-end reading (diagnostic: frames inside each latent group redrawn from the group "
                         f"ends): labeler on reconstructions {g['labeler_on_reconstructions']['accuracy']:.2f}, "
                         f"heading kept {f(g['heading_kept'])}; on the originals redrawn alike (the reading's own "
                         f"ceiling) {g['labeler_on_originals']['accuracy']:.2f}, {f(g['originals_heading_kept'])}")
    return "\n".join(lines)


def plot_vae_eval(rep: dict, path: str | Path, fps_hz: float, title: str = "") -> Path:
    """Per-frame PSNR/SSIM curves above originals (top row) vs reconstructions (bottom row) of one clip."""
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames, rec = rep["_examples"]
    t = frames.shape[1]
    cols = list(range(0, t, max(1, t // 6)))[:7]
    fig = plt.figure(figsize=(14, 6.2))
    ax = fig.add_subplot(3, 1, 1)
    x = np.arange(len(rep["psnr_db"]["per_frame"])) / fps_hz
    ax.plot(x, rep["psnr_db"]["per_frame"], label=f"PSNR (mean {rep['psnr_db']['mean']:.2f} dB)")
    ax.set_ylabel("PSNR (dB)")
    ax2 = ax.twinx()
    ax2.plot(x, rep["ssim"]["per_frame"], color="tab:orange", label=f"SSIM (mean {rep['ssim']['mean']:.3f})")
    ax2.set_ylabel("SSIM")
    ax.set_xlabel("time in clip (s)")
    ax.legend(loc="lower left")
    ax2.legend(loc="lower right")
    ax.set_title(title or f"VAE reconstruction, {rep['clips']} held-out clips")
    top = np.concatenate([frames[0, k] for k in cols], axis=1)
    bottom = np.concatenate([rec[0, k] for k in cols], axis=1)
    for row, (img, name) in enumerate(((top, "original"), (bottom, "reconstruction"))):
        a = fig.add_subplot(3, 1, 2 + row)
        a.imshow(img)
        a.set_axis_off()
        a.set_title(f"{name}, frames {cols}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
