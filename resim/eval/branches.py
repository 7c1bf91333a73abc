"""Counterfactual branches: does a rollout under a command land on the future recorded under that command?

The synthetic world's forks (``resim synth --set fork_fraction=...``) record one history three times, frame for
frame, up to a junction, and then turn left, go straight or turn right. A clip whose history ends before the
split therefore has sibling clips with the *same* history and a different recorded future, and only the
command tells those futures apart. That gives controllability a ground truth that needs no labeler:

* roll the shared history out under each sibling's command;
* measure the distance of each generated future to every sibling's recorded future, in the latent space the
  model works in (mean squared error over the future latent frames);
* the rollout **lands on** the sibling it is nearest to; it is right when that sibling's recorded command is
  the command it was rolled out under.

Why latents and not the flow labeler on decoded video (``resim.eval.command_following``): the labeler reads the turn
off decoded pixels, so a VAE that smears motion caps it. On the shipped synthetic-world VAE the recorded
futures themselves, encoded and decoded, lose much of their heading (docs/models/synth-vae.md, "Limitations"), and
a model that had memorised a fork's three branches steered its latents to the right one while every decoded
rollout read "forward" (docs/lab/2026-11-26-synth-world-stage-chain.md, "Experiments beside the chain").
Nearest-branch matching reads the model itself; the labeler's reading stays the product's headline number.

Chance is ``1 / (number of siblings)`` per history, averaged; the **null prompt** rolled out from the same history
is scored against each sibling's command as a control (a model that ignores the command sits at chance there too,
by construction). A history is counted once per sibling clip: siblings are different posterior samples of the same
frames, so each gives its own rollouts.

Nearest-sibling scoring has a weakness: where one sibling's recorded future is closest to any bland future (on
seed 1003's trajectory forks a motionless future, the last history latent repeated, is nearest the left-turn
sibling in 9 of 13 histories and never the right), a model whose rollouts are weakly conditioned lands there
whatever it was given (docs/lab/2026-11-26-synth-world-stage-chain.md, stage 6). The null prompt shows where the
pull lies but does not remove it. The **swap test** reads the same rollouts without that pull: for each history and
each pair of asked conditions ``(a, b)``, the pair is right when the matching assignment is nearer than the swapped
one, ``d(g_a, r_a) + d(g_b, r_b) < d(g_a, r_b) + d(g_b, r_a)``, which is ``<g_a - g_b, r_a - r_b> > 0``: the two
rollouts differ the way the two recorded futures differ. A shared pull moves ``g_a`` and ``g_b`` alike and
cancels. A model blind to the condition makes ``g_a`` and ``g_b`` exchangeable (or equal, under the same noise: a
tie, counted 1/2), so chance is exactly 0.5.
"""
from __future__ import annotations

import hashlib
from collections import defaultdict
from typing import Any, Sequence

import numpy as np

from resim.shards.schema import COMMANDS


def counterfactual_groups(clips: Sequence[Any]) -> list[list[int]]:
    """Indices of clips grouped by identical history frames, keeping the groups with more than one recorded
    command (a fork's split seen from before it). Compares the frames, not the latents: the pipeline encodes with
    a posterior *sample* (as CogVideoX trains), so one history's latents differ from clip to clip."""
    groups: dict[str, list[int]] = defaultdict(list)
    for i, c in enumerate(clips):
        groups[hashlib.sha256(np.ascontiguousarray(c.frames[:c.num_history_frames]).tobytes()).hexdigest()].append(i)
    return [g for g in groups.values() if len({clips[i].command for i in g}) > 1]


def counterfactual_clips(clips: Sequence[Any]) -> tuple[list[int], int]:
    """Indices of the clips of :func:`counterfactual_groups` and the number of such histories."""
    keep = counterfactual_groups(clips)
    return sorted(i for g in keep for i in g), len(keep)


def branch_matching(generated: dict[str, np.ndarray], recorded: np.ndarray, commands: Sequence[str],
                    groups: Sequence[Sequence[int]], null_key: str | None = None) -> dict:
    """Score rollouts by the sibling future they land on.

    Args:
        generated: command (and ``null_key``) -> ``(N, F, C, h, w)`` float future latents of every clip's rollout
            under that command (the history of clip ``i`` rolled out).
        recorded: ``(N, F, C, h, w)`` the clips' recorded future latents.
        commands: the N clips' recorded commands.
        groups: counterfactual groups of clip indices (:func:`counterfactual_groups`).
    Returns: ``{"commanded": {matrix, n, accuracy, per_command}, "null_prompt": {...}, "chance", "histories",
        "mean_distance": {"own": d, "other": d}}``; ``matrix[i][j]``: rollouts under ``COMMANDS[i]`` landing on the
        sibling recorded under ``COMMANDS[j]``. Only commands some sibling recorded are asked of a history.
    """
    if not groups:
        raise ValueError("no counterfactual groups: no two clips share a history with different commands")
    m = np.zeros((3, 3), dtype=int)
    m_null = np.zeros((3, 3), dtype=int)
    chance, own_d, other_d = [], [], []
    for g in groups:
        by_cmd, asked = _siblings(g, commands)
        for i in g:                                          # each sibling's own rollouts of the shared history
            for c in asked:
                d = _distances(generated[c][i], recorded, by_cmd, asked)
                landed = asked[int(np.argmin(d))]
                m[COMMANDS.index(c), COMMANDS.index(landed)] += 1
                chance.append(1 / len(asked))
                own_d.append(d[asked.index(c)])
                other_d.extend(x for k, x in enumerate(d) if asked[k] != c)
                if null_key is not None:
                    dn = _distances(generated[null_key][i], recorded, by_cmd, asked)
                    m_null[COMMANDS.index(c), COMMANDS.index(asked[int(np.argmin(dn))])] += 1
    out = {"commanded": _confusion(m), "chance": float(np.mean(chance)), "histories": len(groups),
           "mean_distance": {"own_branch": float(np.mean(own_d)), "other_branches": float(np.mean(other_d))}}
    if null_key is not None:
        out["null_prompt"] = _confusion(m_null)
    out["swap_test"] = swap_test(generated, recorded, commands, groups)
    return out


def swap_test(generated: dict[str, np.ndarray], recorded: np.ndarray, commands: Sequence[str],
              groups: Sequence[Sequence[int]]) -> dict:
    """The swap test of the module docstring, on :func:`branch_matching`'s arguments.

    Returns ``{"accuracy", "n", "left_right": {"accuracy", "n"}, "mean_cosine", "histories_above_chance",
    "histories"}``: ``n`` pairs (each sibling clip's rollouts x each pair of asked commands); ``left_right`` the
    pairs of the two turns alone; ``mean_cosine`` of ``g_a - g_b`` with ``r_a - r_b`` (0 for a blind model, 1 for
    one that moves exactly as the recorded futures differ, whatever the scale); ``histories_above_chance``: the
    histories whose pairs score above 0.5. Ties (identical rollouts) count 1/2."""
    scores, lr, cos, per_history = [], [], [], []
    for g in groups:
        by_cmd, asked = _siblings(g, commands)
        rec = {c: np.mean([recorded[j] for j in by_cmd[c]], axis=0, dtype=np.float64).ravel() for c in asked}
        mine = []
        for i in g:
            for x, a in enumerate(asked):
                for b in asked[x + 1:]:
                    dg = np.asarray(generated[a][i], np.float64).ravel() - np.asarray(generated[b][i], np.float64).ravel()
                    dr = rec[a] - rec[b]
                    ip = float(dg @ dr)
                    s = 0.5 if ip == 0 else float(ip > 0)
                    scores.append(s)
                    mine.append(s)
                    if {a, b} == {COMMANDS[0], COMMANDS[2]}:
                        lr.append(s)
                    norm = float(np.linalg.norm(dg) * np.linalg.norm(dr))
                    cos.append(ip / norm if norm > 0 else 0.0)
        if mine:
            per_history.append(float(np.mean(mine)))
    return {"accuracy": float(np.mean(scores)) if scores else None, "n": len(scores),
            "left_right": {"accuracy": float(np.mean(lr)) if lr else None, "n": len(lr)},
            "mean_cosine": float(np.mean(cos)) if cos else None,
            "histories_above_chance": int(sum(p > 0.5 for p in per_history)), "histories": len(per_history)}


def _siblings(group: Sequence[int], commands: Sequence[str]) -> tuple[dict[str, list[int]], list[str]]:
    """A fork's clips by recorded command, and the commands asked of it (those some sibling recorded)."""
    by_cmd: dict[str, list[int]] = defaultdict(list)
    for i in group:
        by_cmd[commands[i]].append(i)
    return by_cmd, [c for c in COMMANDS if c in by_cmd]


def _distances(gen: np.ndarray, recorded: np.ndarray, by_cmd: dict[str, list[int]], asked: list[str]) -> list[float]:
    """Mean squared distance of one generated future to each asked command's recorded futures (the mean over
    that command's siblings, when a fork was recorded more than once)."""
    g = np.asarray(gen, np.float64)
    return [float(np.mean([np.mean((g - recorded[j]) ** 2) for j in by_cmd[c]])) for c in asked]


def _confusion(m: np.ndarray) -> dict:
    n = int(m.sum())
    return {"commands": list(COMMANDS), "matrix": m.tolist(), "n": n,
            "accuracy": float(np.trace(m) / n) if n else None,
            "per_command": {c: (float(m[i, i] / m[i].sum()) if m[i].sum() else None) for i, c in enumerate(COMMANDS)}}


def trajectory_groups(clips: Sequence[Any], groups: Sequence[Sequence[int]]) -> list[list[int]]:
    """The counterfactual groups whose every clip carries its recorded trajectory (the synthetic world's
    CARLA-layout forks; OpenDV-layout clips have none), as lists of indices into ``clips``."""
    return [list(g) for g in groups if all(clips[i].trajectory is not None for i in g)]


def sibling_trajectory_requests(clips: Sequence[Any], groups: Sequence[Sequence[int]]) -> list[tuple[int, str, Any]]:
    """``(clip index, command, trajectory)`` for every rollout the trajectory branches need: each clip's history
    under the recorded trajectory of each sibling, named by that sibling's recorded command (the first sibling
    recorded under it, when a fork was recorded more than once). Only commands some sibling recorded are asked,
    as in :func:`branch_matching`, which then scores these rollouts unchanged: the trajectory, not the command,
    is what was given, and the branch it names is the one it should land on."""
    out = []
    for g in groups:
        first: dict[str, int] = {}
        for i in g:
            first.setdefault(clips[i].command, i)
        for i in g:
            out += [(i, c, clips[first[c]].trajectory) for c in COMMANDS if c in first]
    return out


def format_branches(rep: dict, title: str = "counterfactual branches", given: str = "commanded") -> str:
    """Text lines for ``commands_eval``'s ``branches`` (or ``trajectory_branches``) section."""
    if "skipped" in rep:
        return f"{title}: {rep['skipped']}"
    c, d = rep["commanded"], rep["mean_distance"]
    lines = [f"{title} ({rep['histories']} shared histories; the rollout lands on the nearest "
             f"recorded sibling future, latent MSE; chance {rep['chance']:.2f}):",
             f"  {given:<24} {c['accuracy']:.3f}  (n={c['n']})"]
    if "null_prompt" in rep:
        lines.append(f"  {'null_prompt':<24} {rep['null_prompt']['accuracy']:.3f}  (n={rep['null_prompt']['n']})")
    lines.append(f"  mean distance to the {given} branch {d['own_branch']:.4f}, to the others {d['other_branches']:.4f}")
    sw = rep.get("swap_test")
    if sw and sw["n"]:
        lr = sw["left_right"]
        lines.append(f"  swap test (rollouts differ as the recorded futures do; chance 0.50, no pull): {sw['accuracy']:.3f} "
                     f"(n={sw['n']} pairs), left vs right {lr['accuracy'] if lr['n'] else float('nan'):.3f} (n={lr['n']}); "
                     f"{sw['histories_above_chance']} of {sw['histories']} histories above chance; "
                     f"mean cosine {sw['mean_cosine']:+.3f}")
    return "\n".join(lines)
