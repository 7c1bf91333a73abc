import json

import pytest

from resim.pipeline.sources.episode import SourceError
from resim.pipeline.sources.leaderboard import load_results, outside_lanes_pct, parse_results

REAL = {
    "lb1_transfuser_autopilot_longest6.json": ("lb1", 36),
    "lb1_transfuser_cvpr2021_sample_result.json": ("lb1", 60),
    "lb1_tcp_develop_wph_results_TCP_multi_infraction.json": ("lb1", 1),
    "lb2_b2d_24041_failed_blocked_offroad.json": ("b2d", 1),
    "lb2_b2d_2903_failed_tickruntime_collision.json": ("b2d", 1),
    "lb2_b2d_2201_completed_vehicle_redlight.json": ("b2d", 1),
    "lb2_b2d_18252_completed_pedestrian.json": ("b2d", 1),
    "lb2_b2d_24206_simulation_crashed.json": ("b2d", 1),
    "lb2_b2d_24759_started_no_records.json": ("lb1", 0),   # no records: nothing tells the variant apart
    "lb2_b2d_expert_10857_completed_int_score_route.json": ("b2d", 1),
}


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_results_files_parse(shared_formats, name):
    res = load_results(shared_formats / "leaderboard" / name)
    variant, n = REAL[name]
    assert res.variant == variant and len(res.records) == n
    for r in res.records:
        assert 0.0 <= r.score_penalty <= 1.0
        assert len(r.infraction_names()) == sum(len(v) for v in r.infractions.values())
        o = r.outcome()
        assert o.infraction_score == r.score_penalty
        assert o.hazard == (r.status not in ("Perfect", "Completed") or r.score_penalty < 1.0)


def test_real_values(shared_formats):
    lb = shared_formats / "leaderboard"
    r = load_results(lb / "lb2_b2d_2201_completed_vehicle_redlight.json").records[0]
    assert r.status == "Completed" and r.score_penalty == pytest.approx(0.42)
    assert r.infraction_names().count("collisions_vehicle") == 1 and r.infraction_names().count("red_light") == 1
    assert r.route_number == 2201 and r.save_name.startswith("RouteScenario_2201_rep0_Town12")
    ped = load_results(lb / "lb2_b2d_18252_completed_pedestrian.json").records[0]
    assert ped.score_penalty == pytest.approx(0.5) and "collisions_pedestrian" in ped.infraction_names()
    exp = load_results(lb / "lb2_b2d_expert_10857_completed_int_score_route.json").records[0]
    assert exp.score_route == 100.0 and exp.infraction_names().count("min_speed_infractions") == 20
    crashed = load_results(lb / "lb2_b2d_24206_simulation_crashed.json")
    assert crashed.entry_status == "Crashed" and crashed.global_record == {}
    started = load_results(lb / "lb2_b2d_24759_started_no_records.json")
    assert started.entry_status == "Started" and started.progress == (0, 1) and started.records == []
    tcp = load_results(lb / "lb1_tcp_develop_wph_results_TCP_multi_infraction.json").records[0]
    assert tcp.status == "Failed" and tcp.infraction_names().count("collisions_vehicle") == 4
    msgs = tcp.infractions["outside_route_lanes"]
    assert msgs and outside_lanes_pct(msgs[0]) is not None


def test_malformed_results_are_source_errors(tmp_path):
    with pytest.raises(SourceError, match="no _checkpoint"):
        parse_results({"records": []}, "x.json")
    bad = {"_checkpoint": {"records": [{"route_id": "RouteScenario_1", "status": "Failed", "infractions": {},
                                        "scores": {"score_route": 10, "score_penalty": 1.5, "score_composed": 15}}]}}
    with pytest.raises(SourceError, match=r"x.json record 0.*outside \[0, 1\]"):
        parse_results(bad, "x.json")
    p = tmp_path / "r.json"
    p.write_text(json.dumps(bad)[:20])
    with pytest.raises(SourceError, match="malformed results JSON"):
        load_results(p)


def test_transient_read_error_propagates_bad_files_do_not(tmp_path, monkeypatch):
    import errno
    import pathlib

    with pytest.raises(SourceError, match="cannot read results file"):             # not there: bad data
        load_results(tmp_path / "missing.json")
    p = tmp_path / "r.json"
    p.write_text("{}")

    def eio(self, *a, **k):
        raise OSError(errno.EIO, "Input/output error")
    monkeypatch.setattr(pathlib.Path, "read_text", eio)
    with pytest.raises(OSError) as e:                                               # was: SourceError (never retried)
        load_results(p)
    assert not isinstance(e.value, SourceError) and e.value.errno == errno.EIO and str(p) in str(e.value)
