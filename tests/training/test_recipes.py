"""The shipped training recipes (configs/train/<model>/<preset>.yaml): every one resolves into a valid run config,
and a recipe whose names disagree with its file is refused in one line naming the file."""
import argparse

import pytest

from resim.config import ConfigError
from resim.train import cli, presets
from resim.train.presets import PRESETS, load_recipes, recipes_dir
from resim.train.run import resolve_config


@pytest.mark.parametrize("model, preset", [(m, p) for m, table in PRESETS.items() for p in table])
def test_every_shipped_recipe_resolves(model, preset):
    cfg = resolve_config(model, preset)
    assert cfg.model_name == model and cfg.preset == preset


def test_the_recipes_are_the_shipped_folder():
    assert recipes_dir().parts[-2:] == ("configs", "train")
    assert {"tiny", "synth-world", "stage1"} <= set(PRESETS["world"]) and "tiny" in PRESETS["vae"]
    # the first is `--preset`'s default, as before the recipes were files
    assert [next(iter(PRESETS[m])) for m in ("world", "vae", "distill")] == ["tiny", "synth", "synth"]


@pytest.mark.parametrize("text, match", [
    ("model_name: world\npreset: other\n", r"mine\.yaml: model_name 'world' and preset 'other' must be 'world' and 'mine'"),
    ("model_name: vae\npreset: mine\n", r"mine\.yaml: model_name 'vae'"),
    ("- a list\n", r"mine\.yaml: a training recipe must be a mapping"),
])
def test_a_recipe_with_the_wrong_names_is_refused(tmp_path, text, match):
    (tmp_path / "world").mkdir()
    (tmp_path / "world" / "mine.yaml").write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_recipes(tmp_path)
    (tmp_path / "world" / "mine.yaml").write_text("model_name: world\npreset: mine\n")   # the control
    assert load_recipes(tmp_path)["world"]["mine"]["preset"] == "mine"


def test_without_the_recipes_folder_the_cli_still_builds_and_train_says_why(monkeypatch):
    """A job's working dir or a wheel outside a checkout has no configs/train: `resim` must still start (a Ray job
    runs `resim pipeline run` there), and `resim train` says in one line what is missing."""
    p = argparse.ArgumentParser()
    cli.add_train_arguments(p, [])
    assert p.parse_args(["--out", "x"]).preset is None
    monkeypatch.setitem(presets.PRESETS, "world", {})
    with pytest.raises(KeyError, match="no training recipes for world: .* is missing"):
        presets.get_preset("world", "tiny")
