"""resim.models.exported: the one layout (RUN/final/{config.yaml, model.safetensors, ema.safetensors}) and its loader,
on the registry's toy model; the world model, the IDM and the reward model are tested through their callers."""
import pytest
import torch
import yaml
from safetensors.torch import save_file

from resim.models import registry
from resim.models.exported import (ExportError, ExportNotFoundError, find_export, load_exported, read_config,
                               write_export)

TOY = {"dim": 4, "hidden": 8, "num_blocks": 1}


def _run(tmp_path, model_cfg=TOY, name="toy", seed=0):
    torch.manual_seed(seed)
    model = registry.build(name, model_cfg)
    write_export(tmp_path / "run" / "final", model.state_dict(), {"model_name": name, "model": model_cfg})
    return tmp_path / "run", model


def _same(a, b):
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_a_run_its_final_folder_and_the_files_load_the_same_weights(tmp_path):
    run, model = _run(tmp_path)
    for where in (run, run / "final"):
        ex = load_exported(where, expect="toy")
        assert ex.folder == run / "final" and ex.weights.name == "model.safetensors" and ex.model_name == "toy"
        assert _same(ex.model, model) and not ex.model.training
    assert yaml.safe_load((run / "final" / "config.yaml").read_text()) == {"model_name": "toy", "model": TOY}
    assert not list((run / "final").glob("*.tmp"))


def test_ema_is_used_only_when_preferred_and_present(tmp_path):
    run, model = _run(tmp_path)
    assert load_exported(run, prefer_ema=True).weights.name == "model.safetensors"   # none written
    ema = {k: v + 1 for k, v in model.state_dict().items()}
    save_file(ema, str(run / "final" / "ema.safetensors"))
    ex = load_exported(run, prefer_ema=True)
    assert ex.weights.name == "ema.safetensors" and all(torch.equal(ex.model.state_dict()[k], v) for k, v in ema.items())
    assert load_exported(run).weights.name == "model.safetensors"


def test_adapters_see_the_config_and_the_state_of_an_old_format(tmp_path):
    """An old file: other key names and a config without a key the builder needs now; the adapters mend both."""
    run, model = _run(tmp_path)
    old = {"old." + k: v for k, v in model.state_dict().items()}
    save_file(old, str(run / "final" / "model.safetensors"))
    (run / "final" / "config.yaml").write_text(yaml.safe_dump({"model_name": "toy", "model": {"dim": 4}}))
    seen = {}

    def adapt_config(cfg, state):
        seen["cfg"], seen["keys"] = dict(cfg), sorted(state)
        return {**cfg, "hidden": 8, "num_blocks": 1}

    ex = load_exported(run, adapt_config=adapt_config, adapt_state=lambda s, m: {k[4:]: v for k, v in s.items()})
    assert seen == {"cfg": {"dim": 4}, "keys": sorted(old)} and _same(ex.model, model)
    with pytest.raises(ExportError, match="model.safetensors: weights do not match config.yaml"):
        load_exported(run, adapt_config=adapt_config)   # strict: the old names alone do not load


def test_missing_files_name_both_places(tmp_path):
    (tmp_path / "run" / "final").mkdir(parents=True)
    (tmp_path / "run" / "final" / "config.yaml").write_text("model_name: toy\n")
    with pytest.raises(ExportNotFoundError) as e:
        find_export(tmp_path / "run")
    msg = str(e.value)
    assert msg == (f"{tmp_path / 'run'}: expected config.yaml + model.safetensors in it or in "
                   f"{tmp_path / 'run' / 'final'}")


@pytest.mark.parametrize("text, reason", [
    ("model_name: [unclosed\n", "config.yaml: invalid YAML"),
    ("!!python/object/apply:os.system [echo]\n", "config.yaml: invalid YAML"),
    ("- a list\n", "config.yaml: expected a mapping with model_name and model, got list"),
    ("model_name: 3\nmodel: {}\n", "config.yaml: model_name must be a string"),
    ("model_name: toy\nmodel: [1]\n", "config.yaml: model must be a mapping"),
    ("model_name: nosuch\n", "config.yaml: model_name 'nosuch' has no builder in resim.models.registry"),
    ("model_name: toy\nmodel: {dim: 4, bogus: 1}\n", "config.yaml: "),
    ("", "config.yaml: empty"),                       # was: sampled with every default
])
def test_a_bad_config_is_one_line_naming_the_file(tmp_path, text, reason):
    run, _ = _run(tmp_path)
    (run / "final" / "config.yaml").write_text(text)
    with pytest.raises(ExportError) as e:
        load_exported(run)
    msg = str(e.value)
    assert msg.startswith(str(run / "final" / "config.yaml")) and reason in msg and "\n" not in msg, msg


def test_model_name_is_checked_against_the_callers(tmp_path):
    run, _ = _run(tmp_path)
    with pytest.raises(ExportError, match=r"config.yaml: model_name is 'toy', not an IDM run$"):
        load_exported(run, expect="idm", label="an IDM run")
    (run / "final" / "config.yaml").write_text(yaml.safe_dump({"model": TOY}))
    assert read_config(run / "final", default_name="toy").model_name == "toy"   # absent: the caller's default
    with pytest.raises(ExportError, match="model_name is None, not 'toy'"):
        read_config(run / "final", expect="toy")


def test_bad_weights_name_the_file(tmp_path):
    run, _ = _run(tmp_path)
    w = run / "final" / "model.safetensors"
    w.write_bytes(w.read_bytes()[:50])
    with pytest.raises(ExportError, match=f"^{w}: not a readable safetensors file"):
        load_exported(run)
    other, _ = _run(tmp_path / "b", {**TOY, "hidden": 16})
    w.write_bytes((other / "final" / "model.safetensors").read_bytes())
    with pytest.raises(ExportError, match=f"^{w}: weights do not match config.yaml \\(Error"):
        load_exported(run)
