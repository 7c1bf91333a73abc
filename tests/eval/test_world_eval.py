"""`resim train idm` and `resim eval control|planning|quality` end to end on a tiny random world model, the tiny
placeholder VAE and rendered shards: the commands run, write JSON + PNG, and the reports hold what the protocol
says."""
import json

import numpy as np
import pytest
import torch
import yaml

from resim.cli import main
from resim.shards.schema import ClipSpec
from tests.support.shards import write_data_encode


@pytest.fixture(scope="module")
def world(tmp_path_factory, road_world):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("evalworld")
    ds = root / "ds"
    # short clips keep the (CPU-slow) VAE decode cheap: 9 history + 12 future frames (6 latent frames), the
    # 8 waypoints every 0.15 s spanning the 12 future frames
    spec = ClipSpec(fps_hz=10.0, num_history_frames=9, num_future_frames=12, waypoint_dt_s=0.15)
    road_world.write_shards(ds, 2, 21, clip_stride_frames=10, seed=1, spec=spec)
    # a world-model "run" in the trainer's export layout (random init: plumbing, not quality)
    from safetensors.torch import save_file

    from resim.models import registry
    torch.manual_seed(0)
    wm = registry.build("world", {"preset": "tiny"})
    (root / "wm" / "final").mkdir(parents=True)
    save_file({k: v.contiguous() for k, v in wm.state_dict().items()}, str(root / "wm/final/model.safetensors"))
    (root / "wm/final/config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {"preset": "tiny"}}))
    write_data_encode(root / "wm/final")
    for window in ("future", "history"):
        rc = main(["train", "idm", "--shards", str(ds), "--out", str(root / f"idm-{window}"), "--preset", "tiny",
                   "--window", window, "--epochs", "1", "--batch-size", "8",
                   *(["--set", "future_frames=12", "--set", "num_frames=7"] if window == "future" else [])])
        assert rc == 0
    return root, ds


def _common(root, ds, out):
    return ["--checkpoint", str(root / "wm"), "--shards", str(ds), "--out", str(out), "--steps", "2",
            "--no-guidance", "--device", "cpu", "--set", "runtime.batch_size=4"]


def test_idm_run_report_and_split(world):
    root, _ = world
    rep = json.loads((root / "idm-future/idm_report.json").read_text())
    pro = rep["protocol"]
    assert pro["episodes_train"] == 1 and pro["episodes_heldout"] == 1 and pro["clips_heldout"] == 1
    assert {"idm", "constant_velocity"} <= set(rep["heldout"])
    assert (root / "idm-future/final/model.safetensors").is_file() and (root / "idm-future/idm_report.png").is_file()
    hist = json.loads((root / "idm-history/idm_report.json").read_text())
    assert "planner" in hist["heldout"] and hist["model"]["window"] == "history"


def test_control_and_planning_commands(world, capsys):
    root, ds = world
    out = root / "control"
    # the IDM's held-out split is one episode; non-expert trajectories need another: evaluate every clip
    rc = main(["eval", "control", *_common(root, ds, out), "--idm", str(root / "idm-future"), "--all-clips"])
    assert rc == 0
    rep = json.loads((out / "control.json").read_text())
    assert rep["expert"]["n"] == 2 and rep["non_expert"]["n"] == 2 and rep["protocol"]["episodes"] == 2
    assert rep["idm_on_recorded_through_vae"]["n"] == 2
    assert rep["followed"]["rollouts"]["n"] == 4 and len(rep["pairs"][0]["end_m"]) == 5
    assert all(p["clip"] != p["non_expert_from"] for p in rep["pairs"])
    assert (out / "control.png").stat().st_size > 1000
    assert rep["protocol"]["world_model"]["vae_placeholder"] is True
    text = capsys.readouterr().out
    assert "protocol:" in text and "Trajectory Difference" in text

    out2 = root / "planning"
    rc = main(["eval", "planning", *_common(root, ds, out2), "--idm", str(root / "idm-future"),
               "--planner", str(root / "idm-history")])
    assert rc == 0
    rep = json.loads((out2 / "planning.json").read_text())
    for k in ("video_prediction_policy", "vo_planner_history_only", "constant_velocity"):
        assert np.isfinite(rep[k]["ade_m"]) and rep[k]["n"] == rep["protocol"]["clips"]
    # a planner that is not history-only is refused
    assert main(["eval", "planning", *_common(root, ds, out2), "--idm", str(root / "idm-future"),
                 "--planner", str(root / "idm-future")]) == 2


def test_quality_command(world, capsys):
    root, ds = world
    out = root / "quality"
    assert main(["eval", "quality", *_common(root, ds, out), "--metrics", "psnr", "ssim", "dreamsim",
                 "--limit", "1"]) == 0
    rep = json.loads((out / "quality.json").read_text())
    pro = rep["protocol"]
    assert pro["clips"] == 1 and pro["conditioning_frames_excluded"] == 9 and pro["future_frames_scored"] == 12
    assert [r["horizon_s"] for r in rep["per_horizon"]] == [1.0, 2.0]
    assert [r["frames_per_clip"] for r in rep["per_horizon"]] == [10, 2]
    assert "resized" in pro["generated_resize"] and pro["world_model"]["vae_placeholder"] is True
    assert rep["overall"]["dreamsim"].startswith("not available")
    assert (out / "quality.png").stat().st_size > 1000
    # placeholder networks are refused unless asked for
    assert main(["eval", "quality", *_common(root, ds, out), "--metrics", "lpips", "--limit", "1"]) == 2


def test_rollouts_report_progress_at_most_every_log_every_s(monkeypatch):
    """Every `resim eval` command rolls out through WorldRollouts, which prints a progress line after a batch at
    most every log_every_s (60 s by default): a 50-step evaluation on a CPU was silent for a quarter of an hour."""
    from types import SimpleNamespace

    from resim.eval import worldeval

    monkeypatch.setattr(worldeval, "rollout", lambda model, hist, cond, n, cfg, seed, schedule:
                        SimpleNamespace(latents=torch.zeros(hist.shape[0], 4, 1, 1, 1)))
    clips = [_eval_clip(i, f"e{i}") for i in range(5)]
    for every_s, want in ((0.0, ["2 rollouts so far", "4 rollouts so far", "5 rollouts so far"]), (3600.0, [])):
        lines = []
        r = worldeval.WorldRollouts(None, None, None, lambda c: torch.zeros(1, 2, 3), batch_size=2, log=lines.append,
                                    log_every_s=every_s)
        r.generate_latents(clips, [None] * 5, [None] * 5)
        assert [m.split(",")[0] for m in lines] == want


def test_drift_command_rolls_out_past_the_clip(world, capsys):
    root, ds = world
    out = root / "drift"
    assert main(["eval", "drift", *_common(root, ds, out), "--all-clips", "--limit", "1", "--seconds", "3"]) == 0
    rep = json.loads((out / "drift.json").read_text())
    assert rep["generated_frames"] == 30 and [r["t_s"] for r in rep["per_second"]] == [1.0, 2.0, 3.0]
    assert all(np.isfinite(r["drift"]) for r in rep["per_second"]) and set(rep["drift_at"]) == {"1s"}
    assert (out / "drift.png").stat().st_size > 1000 and (out / "drift_strip.png").is_file()
    assert "drift" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="Turning up"):
        main(["eval", "drift", *_common(root, ds, out), "--command", "Turning up"])


def test_drift_is_zero_for_real_frames_and_large_for_grey_blur():
    from resim.eval.drift import drift_curve, real_reference

    rng = np.random.default_rng(0)
    real = [rng.integers(0, 256, (20, 16, 24, 3), dtype=np.uint8) for _ in range(3)]
    ref = real_reference(real)
    same = drift_curve(np.stack(real), 0, 10.0, ref)
    grey = drift_curve(np.full((3, 20, 16, 24, 3), 128, np.uint8), 0, 10.0, ref)
    assert max(r["drift"] for r in same) < 0.2 and min(r["drift"] for r in grey) > 3
    assert [r["t_s"] for r in grey] == [1.0, 2.0]


def test_mixed_geometries_keep_the_most_common_one(capsys):
    from resim.eval.worldeval import EvalClip, _one_geometry

    def clip(key, t_lat, hist, fps):
        return EvalClip(key, key, np.zeros((t_lat, 4, 2, 2), np.float32), None, None, None, hist, fps, True)

    clips = [clip("a", 13, 9, 10.0), clip("b", 3, 1, 2.0), clip("c", 13, 9, 10.0)]
    kept = _one_geometry(clips)
    assert [c.key for c in kept] == ["a", "c"]
    assert "left out clips of other geometries: 1 x latent (3, 4, 2, 2) @ 2 Hz" in capsys.readouterr().err


def test_limit_spreads_clips_over_episodes():
    """--limit takes clips round-robin over episodes: the first N keys would often be one episode, leaving
    no other episode for non-expert trajectories."""
    from resim.eval.worldeval import EvalClip, spread_over_episodes

    clips = [EvalClip(f"{ep}_{i}", ep, np.zeros((1, 1, 1, 1), np.float32), None, None, None, 1, 10.0, True)
             for ep in ("a", "b", "c") for i in range(3 if ep != "c" else 1)]
    assert [c.key for c in spread_over_episodes(clips, 2)] == ["a_0", "b_0"]
    assert [c.key for c in spread_over_episodes(clips, 5)] == ["a_0", "a_1", "b_0", "b_1", "c_0"]
    assert len(spread_over_episodes(clips, 100)) == 7


def _eval_clip(i, ep, frames=21):
    from resim.eval.worldeval import EvalClip

    return EvalClip(f"k{i}", ep, np.zeros((4, 1, 1, 1), np.float32),
                    np.random.default_rng(i).integers(0, 255, (frames, 32, 48, 3), dtype=np.uint8),
                    np.zeros((8, 3), np.float32), None, 9, 10.0, True)


def test_quality_eval_batches_get_the_seeds_of_one_generate_call():
    """quality_eval rolls out one batch at a time; each batch used to restart at seed + 0 (the same starting
    noise for every batch: correlated samples behind FID/FVD)."""
    from resim.eval.quality import QualityConfig
    from resim.eval.worldeval import WorldRollouts, quality_eval

    seen = []

    class Recorded(WorldRollouts):
        def _batch(self, clips, trajs, commands, seed, num_future_latents=None):
            seen.append(seed)
            return torch.from_numpy(np.stack([c.frames for c in clips]))

        def decode(self, clips, latents):          # the "latents" above are the frames
            return latents.numpy()

    clips = [_eval_clip(i, f"e{i % 3}") for i in range(7)]
    r = Recorded(None, None, None, None, seed=5, batch_size=2)
    quality_eval(r, clips, QualityConfig(metrics=("psnr",), num_conditioning_frames=9))
    per_batch = list(seen)
    seen.clear()
    r.generate(clips, [c.trajectory for c in clips], [None] * 7)
    assert per_batch == seen == [5, 7, 9, 11]


def test_idm_window_and_non_expert_pairs_are_checked_before_any_rollout():
    """An IDM whose window does not fit the clips used to fail after every rollout had run; a single-episode
    clip set (e.g. --limit 1) failed with a bare ValueError traceback."""
    from types import SimpleNamespace

    from resim.models.idm import idm_preset
    from resim.eval.worldeval import WorldRollouts, control_eval, non_expert_pairs, planning_eval

    class NoRollouts(WorldRollouts):
        def _batch(self, *a, **k):
            pytest.fail("rolled out before the inputs were checked")

    runner = NoRollouts(None, None, None, None)
    clips = [_eval_clip(0, "a"), _eval_clip(1, "b")]
    idm = SimpleNamespace(cfg=idm_preset("tiny"))          # 21 frames every 2 after the history: 49 frames
    with pytest.raises(ValueError, match=r"IDM \(future window.*does not fit clip k0: .*of a 21-frame clip"):
        control_eval(runner, idm, clips)
    with pytest.raises(ValueError, match="does not fit clip k0"):
        planning_eval(runner, idm, None, clips)
    fits = SimpleNamespace(cfg=idm_preset("tiny", future_frames=12, num_frames=7))
    with pytest.raises(ValueError, match="VO planner .*does not fit"):
        planning_eval(runner, fits, SimpleNamespace(cfg=idm_preset("tiny-history", num_frames=12)), clips)
    with pytest.raises(ValueError, match=r"all of episode 'a'.*--limit"):
        control_eval(runner, fits, clips[:1])
    assert non_expert_pairs(clips) == [1, 0]


def test_limit_zero_is_an_error_not_all_clips(tmp_path):
    """`if limit:` made limit=0 mean "every clip"; None is "every clip", < 1 is an error."""
    from resim.eval.worldeval import eval_clips_from_dataset

    with pytest.raises(ValueError, match="limit must be >= 1"):
        eval_clips_from_dataset(tmp_path, limit=0)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        eval_clips_from_dataset(tmp_path / "nope")


def test_commands_command_reports_the_labeler_through_the_vae(world, capsys, road_world):
    root, _ = world
    # frames at the size the tiny VAE decodes to (8x its latents), as the pipeline stores them
    ds = root / "ds-vae-size"
    spec = ClipSpec(fps_hz=10.0, num_history_frames=9, num_future_frames=12, waypoint_dt_s=0.15)
    road_world.write_shards(ds, 2, 21, clip_stride_frames=10, seed=1, frames_hw=(64, 96), spec=spec)
    out = root / "commands"
    assert main(["eval", "commands", *_common(root, ds, out), "--all-clips", "--set", "commands.group_ends=true"]) == 0
    rep = json.loads((out / "commands.json").read_text())
    fl = rep["flow_labeler"]
    n = rep["protocol"]["clips"]
    # the diagnostic group-end reading: each command's rollouts and both recorded futures, redrawn and read
    ge = rep["flow_labeler_group_ends"]
    assert ge["commanded"]["n"] == 3 * n and ge["recorded_through_vae"]["n"] == ge["recorded_future"]["n"] == n
    assert set(ge["mean_yaw_deg"]) == {*fl["mean_yaw_deg"]} - {"null prompt"}
    # the clips' own latents decoded as a rollout is: the ceiling of any world model through this VAE
    assert fl["recorded_through_vae"]["n"] == fl["recorded_future"]["n"] == n
    assert "recorded through the VAE" in fl["mean_yaw_deg"]
    # every condition's rollouts (and the recorded frames) are also read mirrored left-right
    assert set(fl["mirror_check_deg"]) == set(fl["mean_yaw_deg"]) - {"recorded through the VAE"}
    assert all("recorded_through_vae_flow" in c for c in rep["clips"])
    assert "no counterfactual clips" in rep["branches"]["skipped"]      # the road world has no forks
    printed = capsys.readouterr().out
    assert "recorded_through_vae" in printed and "group-end reading" in printed
    with pytest.raises(SystemExit, match="--counterfactual-only: no two clips .* share a history"):
        main(["eval", "commands", *_common(root, ds, root / "commands-cf"), "--all-clips", "--counterfactual-only"])


def test_protocol_text_gives_a_count_not_a_dump_of_records():
    from resim.eval.report import format_protocol

    skipped = [{"key": f"clip{i}", "reason": "window 'future' needs frames 0..40 of a 9-frame clip"} for i in range(40)]
    text = format_protocol({"skipped": skipped, "samples": 221})
    assert len(text.splitlines()) == 3 and "skipped: 40 (e.g. key: clip0" in text and "clip39" not in text


def test_quality_warnings_are_printed_once(world, capsys, recwarn):
    root, ds = world
    out = root / "quality-fid"
    assert main(["eval", "quality", *_common(root, ds, out), "--metrics", "psnr", "fid",
                 "--allow-placeholder-networks", "--limit", "2"]) == 0
    text = capsys.readouterr()
    said = [line for line in (text.out + text.err).splitlines() if "biased upwards" in line]
    assert said and len(said) == len(set(said)), said          # each warning once (per horizon + overall)
    assert not [w for w in recwarn if "biased" in str(w.message)]


def test_command_loss_command(world, capsys):
    root, ds = world
    out = root / "command-loss"
    args = ["eval", "command-loss", "--checkpoint", str(root / "wm"), "--shards", str(ds), "--out", str(out),
            "--device", "cpu"]
    with pytest.raises(SystemExit, match="--levels 1000 is outside 0..999"):
        main([*args, "--all-clips", "--levels", "1000"])
    assert main([*args, "--all-clips", "--levels", "900", "300"]) == 0
    rep = json.loads((out / "command_loss.json").read_text())
    assert list(rep["levels"]) == ["900", "300"] and (out / "command_loss.png").is_file()
    assert rep["protocol"]["split"] == {"side": "all", "note": "ALL CLIPS of --shards (--all-clips)"}
    n = rep["protocol"]["clips"]
    assert n == len(rep["per_clip"]) >= 1 and all(len(c["loss"]) == 2 and len(c["loss"][0]) == 4
                                                 for c in rep["per_clip"])
    assert sum(sum(row) for row in rep["levels"]["900"]["confusion"]) == n
    assert "command read by the model's own loss" in capsys.readouterr().out


class _MeanIDM(torch.nn.Module):
    """Reads x of every waypoint as the mean pixel of the window / 10: a function of the video alone."""

    def __init__(self):
        from resim.models.idm import idm_preset

        super().__init__()
        self.cfg = idm_preset("tiny", future_frames=12, num_frames=7)
        self.w = torch.nn.Parameter(torch.zeros(1))

    def window(self, v, nh):
        return v[:, nh - 1:].float()

    def forward(self, v):
        out = torch.zeros(len(v), 8, 3)
        out[:, :, 0] = v.mean(dim=(1, 2, 3, 4))[:, None] / 10
        return out


def test_control_floor_through_the_vae_reads_the_decoded_recorded_latents():
    """``idm_on_recorded_through_vae`` is the IDM on the clips' own latents decoded as a rollout is (not on the
    recorded frames, which give ``idm_on_recorded_video``): a VAE that smears the motion shows in it."""
    from resim.eval.worldeval import WorldRollouts, control_eval

    class Fake(WorldRollouts):
        def generate(self, clips, trajs, commands):
            return np.full((len(clips), 21, 32, 48, 3), 30, np.uint8)

        def decode_recorded(self, clips):
            return np.full((len(clips), 21, 32, 48, 3), 50, np.uint8)   # x read: 5 m

    clips = [_eval_clip(0, "a"), _eval_clip(1, "b")]
    for c in clips:
        c.frames[:] = 20                                                  # x read: 2 m
    rep = control_eval(Fake(None, None, None, None), _MeanIDM(), clips)
    assert rep["idm_on_recorded_video"]["trajectory_difference_m"] == pytest.approx(2.0)
    assert rep["idm_on_recorded_through_vae"]["trajectory_difference_m"] == pytest.approx(5.0)
    assert rep["expert"]["trajectory_difference_m"] == pytest.approx(3.0)
    # _eval_clip's trajectories are all 0: no slope to fit (the slopes themselves: the test below)
    assert rep["followed"]["rollouts"] == {"n": 4, "forward_slope": None, "lateral_slope": None}
    assert rep["pairs"][0]["end_m"]["expert_read"] == [3.0, 0.0]


def test_second_bound_tells_a_model_that_follows_its_trajectory_from_one_that_ignores_it():
    """The second Trajectory Difference bound compares the expert rollouts with the trajectory they were given and
    with one they were not (another episode's): a model that draws the given path exactly reads 0, one that draws
    the same video whatever it is given reads ~1."""
    from resim.eval.worldeval import WorldRollouts, control_eval

    class Follows(WorldRollouts):
        def generate(self, clips, trajs, commands):
            return np.stack([np.full((21, 32, 48, 3), int(10 * t[0, 0]), np.uint8) for t in trajs])

        def decode_recorded(self, clips):
            return self.generate(clips, [c.trajectory for c in clips], None)

    class Ignores(Follows):
        def generate(self, clips, trajs, commands):
            return np.full((len(clips), 21, 32, 48, 3), 55, np.uint8)   # x read: 5.5 m whatever is given

    clips = [_eval_clip(0, "a"), _eval_clip(1, "b")]
    for c, x in zip(clips, (3.0, 8.0)):
        c.trajectory[:, 0] = x
        c.frames[:] = int(10 * x)
    good = control_eval(Follows(None, None, None, None), _MeanIDM(), clips)
    assert good["expert"]["trajectory_difference_m"] == pytest.approx(0.0)
    assert good["expert_vs_not_given"]["trajectory_difference_m"] == pytest.approx(5.0)
    assert good["bounds"]["expert_over_not_given"] == pytest.approx(0.0) and good["bounds"]["expert_over_not_given_met"]
    bad = control_eval(Ignores(None, None, None, None), _MeanIDM(), clips)
    assert bad["expert"]["trajectory_difference_m"] == pytest.approx(2.5)
    assert bad["bounds"]["expert_over_not_given"] == pytest.approx(1.0)
    assert not bad["bounds"]["expert_over_not_given_met"] and not bad["bounds"]["expert_over_idm_floor_met"]


def test_end_point_slopes_tell_followed_from_ignored():
    from resim.eval.worldeval import end_point_slopes

    given = np.zeros((6, 8, 3))
    given[:, -1, 0] = [10, 14, 18, 22, 26, 30]       # speeds
    given[:, -1, 1] = [-5, -3, 0, 0, 3, 5]           # turns
    followed = given.copy()
    followed[:, -1, 0] = 0.5 * given[:, -1, 0] + 4     # half the speed differences, an offset
    followed[:, -1, 1] = given[:, -1, 1]
    s = end_point_slopes(followed, given)
    assert s["forward_slope"] == pytest.approx(0.5) and s["lateral_slope"] == pytest.approx(1.0) and s["n"] == 6
    ignored = np.zeros_like(given)
    ignored[:, -1, 0] = 20.0
    s = end_point_slopes(ignored, given)
    assert s["forward_slope"] == pytest.approx(0.0) and s["lateral_slope"] == pytest.approx(0.0)
    assert end_point_slopes(ignored, ignored)["forward_slope"] is None     # nothing to regress on


def test_the_clips_an_idm_can_read_win_over_the_most_common_geometry(tmp_path):
    """A dataset mixing 10-Hz clips with more 2-Hz NAVSIM ones (the demo's): the IDM's evaluations take the clips
    its window fits, not the most common geometry; with no reader, the most common geometry."""
    from resim.eval.worldeval import eval_clips_from_dataset, idm_fits
    from resim.models.idm import InverseDynamicsModel, idm_preset
    from tests.support.training import navsim_spec, write_world_dataset

    root = write_world_dataset(tmp_path / "mixed", num_samples=12, sources=("navsim", "synthetic"),
                               specs={"navsim": navsim_spec()})
    idm = InverseDynamicsModel(idm_preset("tiny"))
    assert {c.fps_hz for c in eval_clips_from_dataset(root)} == {2.0}              # 8 NAVSIM clips of 12
    read = eval_clips_from_dataset(root, fits=idm_fits(idm))
    assert {c.fps_hz for c in read} == {10.0} and len(read) == 4
    assert {c.fps_hz for c in eval_clips_from_dataset(root, fits=lambda c: False)} == {2.0}   # none fits: unchanged
