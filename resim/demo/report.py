"""The demo's HTML report (``resim demo``, resim/demo/run.py): one self-contained page that links the PNG/GIF
outputs of every step and tabulates their JSON reports. It only reads what the steps wrote."""
from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

from resim.config import to_dict


def _img(path: Path, root: Path, caption: str) -> str:
    if not path.is_file():
        return f"<p><em>missing: {html.escape(str(path.relative_to(root)))}</em></p>"
    rel = html.escape(str(path.relative_to(root)))
    return f'<figure><img src="{rel}" style="max-width:100%"><figcaption>{html.escape(caption)}</figcaption></figure>'


def _stats_table(path: Path) -> str:
    """The pipeline's stats.json as two small tables (units; clips per origin and command), not a raw dump."""
    if not path.is_file():
        return ""
    st = json.loads(path.read_text())
    u, ts = st.get("units", {}), st.get("turning_share", {})
    head = (f"<p>Units: {u.get('ok', '?')} ok, {u.get('quarantined', '?')} quarantined of {u.get('total', '?')}. "
            f"Clips: {st.get('clips', {}).get('total', '?')}; turning share {ts.get('before', '?')} before, "
            f"{ts.get('after', '?')} after ReSim's {ts.get('turn_factor', '?')}x over-sampling of turns.</p>")
    by = st.get("clips", {}).get("commands_by_origin", {})
    cmds = sorted({c for v in by.values() for c in v})
    rows = [[html.escape(o), *[v.get(c, 0) for c in cmds], sum(v.values())] for o, v in sorted(by.items())]
    return head + _table(["origin", *cmds, "clips"], rows)


def _reward_metrics(path: Path) -> str:
    if not path.is_file():
        return ""
    meta = json.loads(path.read_text())
    rows = [[split.split("_")[0]] + ["n/a" if m.get(k) is None else _f(m.get(k)) if isinstance(m.get(k), float)
                                      else html.escape(str(m.get(k)))
                                      for k in ("n", "n_hazard", "mae", "spearman", "hazard_auc")]
            for split in ("train_metrics", "heldout_metrics") for m in [meta.get(split) or {}]]
    return (_table(["split", "clips", "hazardous", "MAE", "Spearman", "AUC"], rows)
            + "<p>(n/a: undefined, the split has one class only or too few clips)</p>")


def _f(v, fmt: str = ".3f") -> str:
    return format(v, fmt) if isinstance(v, (int, float)) else html.escape(str(v))


def _table(header: list[str], rows: list[list]) -> str:
    """An HTML table. Header cells are escaped; row cells are printed as given (format/escape them: ``_f``)."""
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    return (f"<table><tr>{th}</tr>" + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
            + "</table>")


def _eval_section(out: Path) -> list[str]:
    """Section 6: the IDM's held-out ADE/FDE vs constant velocity, Trajectory Difference, PSNR/SSIM per horizon."""
    ev = out / "eval"
    parts = ["<h2>7. Evaluation: Trajectory Difference and video quality</h2>",
             "<p>An inverse dynamics model (IDM: video → 8 waypoints) is trained on the shards' 10 Hz clips with "
             "trajectories, split <b>by episode</b>; the world-model evaluations run on clips of the episodes the "
             "IDM held out (the IDM is small and trained here for seconds: its floor is loose).</p>"]
    idm_p = ev / "idm" / "idm_report.json"
    if idm_p.is_file():
        r = json.loads(idm_p.read_text())
        pro = r["protocol"]
        parts.append(f"<h3>IDM</h3><p>{pro['clips_train']} training clips ({pro['episodes_train']} episodes), "
                     f"{pro['clips_heldout']} held-out clips ({pro['episodes_heldout']} episodes: "
                     f"{html.escape(', '.join(pro['heldout_items']))}); validation: {html.escape(pro['validation'])}."
                     "</p>")
        parts += [_table(["held-out", "ADE (m)", "FDE (m)", "yaw err (deg)", "clips"],
                         [[html.escape(k), _f(v["ade_m"]), _f(v["fde_m"]), _f(v["yaw_err_deg"], ".2f"), v["n"]]
                          for k, v in r["heldout"].items()]), _img(ev / "idm" / "idm_report.png", out, "IDM vs constant velocity, held-out")]
    ctl_p = ev / "control" / "control.json"
    if ctl_p.is_file():
        r = json.loads(ctl_p.read_text())
        parts.append(f"<h3>Controllability: Trajectory Difference</h3><p>{r['protocol']['clips']} held-out clips "
                     f"of {r['protocol']['episodes']} episodes, each rolled out under its recorded trajectory "
                     "(expert) and another episode's (non-expert); the IDM reads the trajectory off the generated "
                     "video. <code>idm_on_recorded_video</code> (the IDM on the real frames) is the floor; "
                     "<code>idm_on_recorded_through_vae</code> (on the recorded latents decoded through the VAE) is "
                     "what a world model that predicted the recorded future exactly would score. "
                     "<code>expert_vs_not_given</code>: the expert rollouts read against the other episode's "
                     "trajectory, which they were not given (a model that ignores its trajectory reads the expert "
                     "row near this one).</p>")
        parts.append(_table(["", "L2 mean (m)", "L2 at 4 s (m)", "clips"],
                            [[k, _f(r[k]["trajectory_difference_m"]), _f(r[k]["trajectory_difference_final_m"]),
                              r[k]["n"]] for k in ("expert", "non_expert", "idm_on_recorded_video",
                                                   "idm_on_recorded_through_vae", "expert_vs_not_given",
                                                   "recorded_video_vs_not_given") if k in r]))
        if "bounds" in r:
            b = r["bounds"]
            parts.append(f"<p>Bounds: expert / IDM floor {_f(b['expert_over_idm_floor'], '.2f')} (target &le; 1.5); "
                         f"expert / the same rollouts against a trajectory not given "
                         f"{_f(b['expert_over_not_given'], '.2f')} (target &lt; 0.5; the recorded video itself reads "
                         f"{_f(b['recorded_video_over_not_given'], '.2f')} with this IDM).</p>")
        ca = r["command_accuracy"]
        acc = (html.escape(ca) if isinstance(ca, str) else ", ".join(
            f"{html.escape(k)}: {_f(v['accuracy'], '.2f')} (n={v['n']})" for k, v in ca.items()))
        parts += [f"<p>Command accuracy (optical-flow labeler on the generated future): {acc}</p>",
                  _img(ev / "control" / "control.png", out, "Trajectory Difference")]
    q_p = ev / "quality" / "quality.json"
    if q_p.is_file():
        r = json.loads(q_p.read_text())
        pro = r["protocol"]
        parts.append(f"<h3>Video quality</h3><p>{pro['clips']} held-out clips, {pro['conditioning_frames_excluded']} "
                     f"history frames excluded, {pro['future_frames_scored']} future frames scored at "
                     f"{pro['metric_resolution_hw']} ({html.escape(str(pro.get('generated_resize')))}). PSNR and "
                     "SSIM only: FID, FVD and LPIPS need the standard network weights (docs/eval.md), which the "
                     "demo does not download.</p>")
        parts += [_table(["horizon", "frames/clip", "PSNR (dB)", "SSIM"],
                         [[f"{row['from_s']:g}–{row['horizon_s']:g} s", row["frames_per_clip"],
                           _f(row.get("psnr"), ".2f"), _f(row.get("ssim"))] for row in r["per_horizon"]]), _img(ev / "quality" / "quality.png", out, "PSNR / SSIM vs prediction horizon")]
    parts.append("<p>Full reports: " + ", ".join(
        f'<a href="{html.escape(str(p.relative_to(out)))}">{html.escape(str(p.relative_to(out)))}</a>'
        for p in (idm_p, ctl_p, q_p) if p.is_file()) + "</p>")
    return parts


def _closed_loop_section(out: Path) -> list[str]:
    """Section 8: the shipped policy and its degraded versions in the true world and inside the world model."""
    d = out / "eval" / "closed_loop"
    p = d / "closed_loop.json"
    if not p.is_file():
        return []
    r = json.loads(p.read_text())
    pro = r["protocol"]
    keys = list(r["readings"].items())   # (report key, label) of the readings the run made
    first = r[keys[0][0]]["per_policy"]
    rows = [[html.escape(n), f"{first[n]['true']:.1f} [{first[n]['true_rank']}]",
             *[f"{r[k]['per_policy'][n]['model']:.1f} [{r[k]['per_policy'][n]['model_rank']}]" for k, _ in keys]]
            for n in r["policies"]]
    def spread(k: str) -> float:
        vals = [v["model"] for v in r[k]["per_policy"].values()]
        return max(vals) - min(vals)

    # a reading whose policy means lie within a point of each other ranks by noise: say so, not a rho
    rho = [[html.escape(label), _f(r[k]["spearman"], ".2f"),
            "n/a" if not r[k]["ci95"] else f"[{r[k]['ci95'][0]:.2f}, {r[k]['ci95'][1]:.2f}]"]
           if spread(k) >= 1.0 else [html.escape(label), "—", "the reading does not separate the policies "
                                                                f"(spread {spread(k):.2f} points)"]
           for k, label in keys]
    cfg = pro["config"]
    return [
        "<h2>8. A policy driving inside the world model (closed loop)</h2>",
        f"<p>The shipped pixel policy (<code>configs/models/synth-policy</code>) and versions of it degraded by "
        f"design drive {len(r['states'])} fork worlds of seed {cfg['seed']} (never trained on) for "
        f"{cfg['seconds']:g} s after a {cfg['history_s']:g}-s expert history, deciding every "
        f"{cfg['decision_s']:g} s: in the <b>true simulator</b> (scored by its infraction rules: 100 = the expert) "
        "and <b>inside the world model</b>, which generates what the policy sees next under the policy's own "
        "waypoints (it is not told the route's command: the waypoints alone steer it). The world model's verdict is read off its video by the shipped IDM "
        "(<code>synth-idm</code>: the driven path laid on the map, route completion × share inside the lane) and by "
        "the Video2Reward trained in section 3 (tiny, minutes of training: a weak reading). The same readings on "
        "the true frames show how much of a disagreement is the reader's. A small version of "
        "<code>resim eval closed-loop</code> (docs/closed_loop.md: 6 policies, 6 states, 8 s).</p>",
        _table(["policy", "true score [rank]", *[label for _, label in keys]], rows),
        "<p>Spearman's rank correlation with the true scores across policies (95 % bootstrap over starting "
        "states; with this few states and policies it is an illustration, not a measurement):</p>",
        _table(["reading", "Spearman", "95 % CI"], rho),
        _img(d / "closed_loop_strip.png", out, "first starting state: each policy in the true world (upper row) "
                                               "and inside the world model (lower row), every 2 s"),
        _img(d / "closed_loop.png", out, "true score vs each reading, one point per policy"),
    ]


def _commands_section(out: Path, cfg: Any) -> list[str]:
    """Section 4: one held-out history rolled out under the three commands, and the command accuracy table."""
    d = out / "eval" / "commands"
    p = d / "commands.json"
    if not p.is_file():
        return []
    r = json.loads(p.read_text())
    fl = r["flow_labeler"]
    rows = [[html.escape(name), _f(fl[k]["accuracy"], ".2f"), fl[k]["n"],
             ", ".join(f"{html.escape(c.split()[-1])} {_f(v, '.2f')}" for c, v in fl[k]["per_command"].items())]
            for name, k in (("commanded (left / forward / right)", "commanded"),
                            ("null prompt (control: 1/3 = ignores the command)", "null_prompt"),
                            ("recorded future (the labeler's ceiling)", "recorded_future"),
                            ("recorded future through the VAE (the ceiling of any world model with this VAE)",
                             "recorded_through_vae")) if k in fl]
    fid = [[f"{x['horizon_s']:g} s", _f(x["psnr_model"], ".2f"), _f(x["psnr_copy_last_frame"], ".2f"),
            _f(x["ssim_model"]), _f(x["ssim_copy_last_frame"])] for x in r["fidelity"]["per_horizon"]]
    return [
        "<h2>4. Does the world model follow the command?</h2>",
        f"<p>World model: <code>{html.escape(cfg.world_model or 'the demo run')}</code>. "
        f"{r['protocol']['clips']} histories of the demo's world ({r['protocol']['episodes']} episodes, none of "
        "which the shipped model trained on), each rolled out under each command with no trajectory; the "
        "optical-flow labeler that labels real video reads which way each generated future turns.</p>",
        _img(d / "commands.gif", out, "recorded future | Turning left | Moving forward | Turning right "
                                      "(one history recorded going straight: the turns are counterfactual)"),
        _img(d / "commands_strip.png", out, "the same rollouts every 0.8 s"),
        _table(["condition", "accuracy", "rollouts", "per command"], rows),
        _img(d / "commands.png", out, "confusion matrices and PSNR vs horizon"),
        "<p>Fidelity of the rollout under the recorded command against the recorded future:</p>",
        _table(["horizon", "PSNR model", "PSNR copy-last-frame", "SSIM model", "SSIM copy-last-frame"], fid),
    ]


def write_report(out: Path, cfg: Any, timings: dict[str, float], key: str) -> Path:
    """One self-contained HTML page linking the PNG/GIF outputs of every step."""
    parts = [
        "<!doctype html><meta charset='utf-8'><title>resim demo</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}figure{margin:1em 0}"
        "pre{background:#f4f4f4;padding:.5em;overflow:auto}td,th{padding:2px 8px}</style>",
        "<h1>resim demo</h1>",
        "<p>The rollouts and evaluations use the <b>shipped synthetic-world models</b> "
        "(<code>configs/models/synth-vae</code>, <code>configs/models/synth-world</code>; and in section 8 "
        "<code>synth-policy</code>, <code>synth-idm</code>; model cards in docs/models/), trained on worlds of "
        "other seeds. The world model and Video2Reward in section 3 are "
        "trained here for minutes, to show the machinery. T5 and DINOv2 are tiny random-init placeholders.</p>"
        if cfg.world_model else
        "<p>The rollouts use the world model trained here for minutes (<code>world_model: \"\"</code>): expect "
        "noise.</p>",
        "<h2>Steps</h2>", _table(["step", "seconds"], [[html.escape(k), f"{v:.1f}"] for k, v in timings.items()]),
        "<h2>1. Synthetic world</h2>", _img(out / "world/contact_sheet.png", out, "a few synthetic episodes"),
        "<h2>2. Pipeline → shards</h2>", _img(out / "shards/report.png", out, "pipeline report"),
        _stats_table(out / "shards/stats.json"),
        "<h2>3. Training (here, for minutes: the machinery)</h2>",
        _img(out / "world_model/loss_curve.png", out, "world model loss (the demo's own run)"),
        _img(out / "reward_model/trainer/loss_curve.png", out, "Video2Reward loss"),
        _img(out / "reward_model/heldout_pred_vs_true.png", out, "Video2Reward: held-out predicted vs true infraction score"),
        _reward_metrics(out / "reward_model/final/meta.json"),
    ]
    parts += _commands_section(out, cfg)
    parts += [f"<h2>5. Rollouts from history <code>{html.escape(key)}</code> (resim sample)</h2>"]
    for name in ("left", "forward", "right"):
        d = out / "samples" / name
        gifs = sorted(d.glob("*.gif"))
        sheets = sorted(d.glob("*contact*.png")) or sorted(d.glob("*.png"))
        parts.append(f"<h3>{name}</h3>")
        if gifs:
            parts.append(_img(gifs[0], out, f"rollout, command: {name}"))
        if sheets:
            parts.append(_img(sheets[0], out, "contact sheet"))
    parts += ["<h2>6. Planning with Video2Reward</h2>"]
    pngs = sorted((out / "plan").glob("*.png"))
    if pngs:
        parts.append(_img(pngs[0], out, "imagined futures per candidate, with reward"))
    ranking = out / "plan" / "ranking.json"
    if ranking.is_file():
        rows = json.loads(ranking.read_text())
        parts.append(_table(["rank", "candidate", "command", "reward"],
                            [[r["rank"], html.escape(r["name"]), html.escape(str(r["command"])), f"{r['reward']:.4f}"]
                             for r in rows]))
    parts += _eval_section(out)
    parts += _closed_loop_section(out)
    parts.append("<h2>Config</h2><details><summary>the demo's resolved config (also demo_config.yaml)</summary>"
                 f"<pre>{html.escape(json.dumps(to_dict(cfg), indent=2))}</pre></details>")
    path = out / "report.html"
    path.write_text("\n".join(parts))
    return path
