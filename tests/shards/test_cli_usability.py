"""`resim shards ...` usability: sample keys from the CLI, quiet `| head`, non-datasets refused like verify does,
preview into an existing folder, an example in every subcommand's help."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from resim.cli import build_parser, main
from resim.shards.manifest import read_manifest

REPO = Path(__file__).resolve().parents[2]
PY = [sys.executable, "-m", "resim"]


def test_ls_samples_lists_keys_with_source_command_shard(dataset, capsys):
    rows = read_manifest(dataset).to_pylist()
    assert main(["shards", "ls", str(dataset), "--samples", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert [r["key"] for r in got] == [r["key"] for r in rows]
    assert got[0] == {k: rows[0][k] for k in ("key", "source", "command", "shard")}
    src = rows[0]["source"]
    assert main(["shards", "ls", str(dataset), "--samples", "--source", src, "--limit", "1", "--json"]) == 0
    assert [r["key"] for r in json.loads(capsys.readouterr().out)] == [rows[0]["key"]]
    assert main(["shards", "ls", str(dataset), "--samples", "--limit", "2"]) == 0
    out = capsys.readouterr().out
    assert rows[0]["key"] in out and rows[2]["key"] not in out and f"2 of {len(rows)} samples" in out
    # a key listed by ls is what show takes
    assert main(["shards", "show", str(dataset), rows[0]["key"], "--json"]) == 0
    assert main(["shards", "ls", str(dataset), "--limit", "2"]) == 2       # --limit/--source go with --samples


def test_help_texts_asking_for_a_key_say_how_to_list_keys(capsys):
    p = build_parser()
    for argv in (["shards", "show", "--help"], ["shards", "preview", "--help"]):
        with pytest.raises(SystemExit):
            p.parse_args(argv)
        assert "resim shards ls DIR --samples" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["shards", "schema"], ["shards", "ls", "{ds}", "--json"],
                                  ["shards", "ls", "{ds}", "--samples"]])
def test_a_closed_pipe_is_quiet(dataset, argv):
    """`resim shards schema | head -1`: no BrokenPipeError traceback, no "error: [Errno 32] Broken pipe"."""
    argv = [a.replace("{ds}", str(dataset)) for a in argv]
    p = subprocess.Popen([*PY, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO)
    p.stdout.close()              # the reader is gone before the command writes (`head` that already exited)
    err = p.stderr.read().decode()
    p.wait(timeout=60)
    assert err == "", err
    assert p.returncode == 141    # 128 + SIGPIPE, like a C tool killed by the signal


@pytest.mark.parametrize("cmd", ["ls", "stats", "show", "preview"])
def test_a_folder_that_is_not_a_dataset_is_an_error_like_verify(tmp_path, capsys, cmd):
    (tmp_path / "opendv").mkdir()           # e.g. a `resim synth` world
    (tmp_path / "ground_truth.json").write_text("{}")
    extra = ["somekey"] if cmd in ("show", "preview") else []
    assert main(["shards", cmd, str(tmp_path), *extra]) == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [f"resim shards {cmd}: error: {tmp_path} has no shards/ folder (not a shard dataset; "
                                "`resim pipeline run` writes one)"]
    assert main(["shards", "verify", "-q", str(tmp_path)]) == 1
    assert "has no shards/ folder" in capsys.readouterr().out


def test_preview_into_an_existing_folder_writes_key_png_there(dataset, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    pytest.importorskip("cv2")
    key = read_manifest(dataset)["key"].to_pylist()[0]
    folder = tmp_path / "previews"
    folder.mkdir()
    assert main(["shards", "preview", str(dataset), key, "--out", str(folder)]) == 0
    printed = capsys.readouterr().out.strip()
    assert Path(printed) == folder / f"{key}.png" and (folder / f"{key}.png").is_file()
    assert not Path(f"{folder}.png").exists()
    # a trailing slash names a folder even when it does not exist yet
    assert main(["shards", "preview", str(dataset), key, "--out", str(tmp_path / "new") + "/"]) == 0
    assert Path(capsys.readouterr().out.strip()) == tmp_path / "new" / f"{key}.png"


@pytest.mark.parametrize("cmd", ["ls", "stats", "show", "verify", "preview", "schema"])
def test_every_shards_subcommand_has_a_description_and_an_example(cmd, capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["shards", cmd, "--help"])
    out = capsys.readouterr().out
    assert f"resim shards {cmd} " in out.split("options:")[-1]     # an example after the options
    head = out.split("options:")[0].split("\n\n")
    assert len(head) >= 2 and head[1].strip(), out             # a description paragraph after the usage
