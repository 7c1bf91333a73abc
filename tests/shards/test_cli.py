"""`resim shards ...` end to end (in-process, through resim.cli.main)."""
import json
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from resim.cli import main
from resim.shards import layout
from resim.shards.manifest import read_indexes

REPO = Path(__file__).resolve().parents[2]


def test_ls(dataset, capsys):
    assert main(["shards", "ls", str(dataset)]) == 0
    out = capsys.readouterr().out
    assert "unitA-00000.tar" in out and "3 shards, 10 samples" in out
    assert main(["shards", "ls", str(dataset), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["num_samples"] for r in rows] == [4, 4, 2] and all(r["committed"] for r in rows)


def test_stats_json(dataset, base_dataset, capsys):
    qdir = layout.quarantine_dir(dataset)
    qdir.mkdir()
    pq.write_table(pa.table({"item": ["a.mp4", "b.mp4"], "source": ["opendv", "opendv"],
                             "stage": ["decode", "label"], "reason": ["truncated file", "too short"],
                             "attempts": [1, 2]}), qdir / "part-0.parquet")
    assert main(["shards", "stats", str(dataset), "--json"]) == 0
    st = json.loads(capsys.readouterr().out)
    samples = base_dataset[1]
    assert st["num_samples"] == 10 and st["num_shards"] == 3
    assert st["by_source"] == {s: sum(x["meta.json"]["source"] == s for x in samples)
                               for s in ("carla", "navsim", "opendv", "synthetic")}
    assert st["by_hazard"]["null"] == sum(x["meta.json"]["hazard"] is None for x in samples)
    assert st["turning_share"] == pytest.approx(sum(x["meta.json"]["is_turning"] for x in samples) / 10)
    assert st["quarantine"]["num_items"] == 2 and st["quarantine"]["by_stage"] == {"decode": 1, "label": 1}
    bps = st["bytes_per_sample"]
    assert set(bps) >= {"meta.json", "latent.npy", "traj.npy", "frames.mp4", "dino.npy", "prompt_table_amortised",
                        "total"}
    assert bps["dino.npy"] > 0 and bps["total"] == pytest.approx(bps["in_shards"] + bps["prompt_table_amortised"])
    assert bps["in_shards"] * 10 == sum(i["bytes"] for i in read_indexes(dataset))
    assert st["latent"]["dtypes"] == {"float16": 5, "bfloat16": 5}
    assert st["prompt_table"]["num_prompts"] == 4
    assert {e["role"] for e in st["prompt_table"]["entries"]} == {"command", "null"}
    assert main(["shards", "stats", str(dataset)]) == 0
    assert "turning share" in capsys.readouterr().out


def test_stats_shows_the_quality_columns_and_plots_them(dataset, base_dataset, tmp_path, capsys):
    png = tmp_path / "q.png"
    assert main(["shards", "stats", str(dataset), "--json", "--plot", str(png)]) == 0
    st = json.loads(capsys.readouterr().out)                     # the JSON stays parseable: the path goes to stderr
    lum = sorted(x["meta.json"]["luma_mean_8bit"] for x in base_dataset[1])
    q = st["quality"]["luma_mean_8bit"]
    assert q["n"] == 10 and q["min"] == pytest.approx(lum[0], abs=1e-3) and q["max"] == pytest.approx(lum[-1], abs=1e-3)
    assert st["quality"]["flow_quality"]["p50"] == 1.0 and png.stat().st_size > 10_000
    assert main(["shards", "stats", str(dataset)]) == 0
    assert "per-clip quality" in capsys.readouterr().out


def test_stats_counts_warning_rows_apart_from_quarantined_items(dataset, capsys):
    """Rows with status warning (the unit was used) are not quarantined items; they are reported as warnings."""
    qdir = layout.quarantine_dir(dataset)
    qdir.mkdir()
    pq.write_table(pa.table({
        "item": ["a.mp4", "b.mp4#f0000040", "c", "d"], "unit_id": ["ua", "ub", "uc", "uc"],
        "source": ["opendv", "opendv", "synthetic/carla", "synthetic/carla"], "stage": ["cut", "label", "cut", "cut"],
        "status": ["quarantined", "dropped", "warning", "warning"],
        "reason": ["truncated file", "NaN poses", "NaN compass interpolated", "no results record"],
        "attempts": pa.array([1, 1, 1, 1], pa.int32())}), qdir / "u.parquet")
    assert main(["shards", "stats", str(dataset), "--json"]) == 0
    st = json.loads(capsys.readouterr().out)
    assert st["quarantine"]["num_items"] == 2 and st["quarantine"]["by_stage"] == {"cut": 1, "label": 1}
    assert {r["status"] for r in st["quarantine"]["items"]} == {"quarantined", "dropped"}
    assert st["warnings"]["num_items"] == 2 and st["warnings"]["by_source"] == {"synthetic/carla": 2}
    assert main(["shards", "stats", str(dataset)]) == 0
    out = capsys.readouterr().out
    assert "quarantined items: 2" in out and "warnings: 2" in out and "1 x NaN compass interpolated" in out


def test_show(dataset, capsys):
    key = read_indexes(dataset)[0]["keys"][1]
    assert main(["shards", "show", str(dataset), key, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["meta"]["key"] == key and out["fields"]["latent.npy"]["shape"] == out["meta"]["latent_shape"]
    assert main(["shards", "show", str(dataset), "nope"]) == 1


def test_verify_exit_codes(dataset, capsys):
    assert main(["shards", "verify", str(dataset), "-q"]) == 0
    assert "OK" in capsys.readouterr().out
    p = layout.shards_dir(dataset) / "unitA-00000.tar"
    p.write_bytes(p.read_bytes()[:-4000])
    assert main(["shards", "verify", str(dataset), "-q"]) == 1
    assert "shard unitA-00000.tar" in capsys.readouterr().out


def test_preview_writes_png(dataset, tmp_path, capsys):
    key = read_indexes(dataset)[0]["keys"][0]
    out = tmp_path / "p.png"
    assert main(["shards", "preview", str(dataset), key, "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert main(["shards", "preview", str(dataset), "--random", "2", "--out", str(tmp_path / "r")]) == 0
    assert len(list((tmp_path / "r").glob("*.png"))) == 2


def test_light_import_and_help():
    """`shards` and its CLI import without torch, ray or cv2."""
    code = ("import sys, resim.shards.cli, resim.shards.reader, resim.shards.writer, resim.shards.verify, resim.shards.stats, resim.shards.prompts, "
            "resim.shards.video, resim.shards.preview; from resim.cli import build_parser; build_parser(); "
            "bad = [m for m in ('torch', 'ray', 'cv2', 'matplotlib') if m in sys.modules]; print(bad)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True,
                       env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert r.stdout.strip() == "[]"
    r = subprocess.run([sys.executable, "-m", "resim", "shards", "stats", "--help"], capture_output=True, text=True,
                       cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}, check=True)
    assert "bytes_per_sample" in r.stdout and "turning_share" in r.stdout


def test_format_doc_covers_schema():
    from resim.shards.schema import MANIFEST_COLUMNS, MEMBERS, META_FIELDS, make_key

    doc = (REPO / "docs" / "data_format.md").read_text()
    for f in META_FIELDS:
        assert f"`{f.name}`" in doc, f.name
    for ext in MEMBERS:
        assert f"`KEY.{ext}`" in doc, ext
    for c in MANIFEST_COLUMNS:
        assert f"`{c}`" in doc, c
    assert make_key("opendv", "city/drive_01.mp4", 120) in doc  # the worked key example is right
