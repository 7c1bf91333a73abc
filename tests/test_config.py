from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import pytest

from resim.config import ConfigError, apply_overrides, config_hash, from_dict, load, save, to_dict


@dataclass
class Inner:
    fps_hz: float = 10.0
    name: Literal["a", "b"] = "a"


@dataclass
class Outer:
    root: Optional[Path] = None
    steps: int = 3
    inner: Inner = field(default_factory=Inner)
    tags: tuple[str, ...] = ()


def test_round_trip_and_hash(tmp_path):
    cfg = from_dict(Outer, {"steps": 5, "inner": {"fps_hz": 2}, "tags": ["x"]})
    assert cfg.inner.fps_hz == 2.0 and cfg.tags == ("x",)
    p = save(cfg, tmp_path / "c.yaml")
    again = load(Outer, p)
    assert to_dict(again) == to_dict(cfg)
    assert config_hash(again) == config_hash(cfg)
    assert config_hash(from_dict(Outer, {"steps": 6})) != config_hash(cfg)


def test_unknown_key_names_full_path():
    with pytest.raises(ConfigError, match=r"inner\.fps"):
        from_dict(Outer, {"inner": {"fps": 3}})


def test_wrong_type_and_literal():
    with pytest.raises(ConfigError, match="steps"):
        from_dict(Outer, {"steps": "many"})
    with pytest.raises(ConfigError, match="inner.name"):
        from_dict(Outer, {"inner": {"name": "c"}})


def test_overrides_parse_yaml_values():
    d = apply_overrides({}, ["inner.fps_hz=2.5", "steps=7", "tags=[a, b]"])
    cfg = from_dict(Outer, d)
    assert cfg.inner.fps_hz == 2.5 and cfg.steps == 7 and cfg.tags == ("a", "b")


def test_yaml_errors_name_the_file_or_the_override(tmp_path):
    from resim.config import ConfigError, load

    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\nb: 3\n")
    with pytest.raises(ConfigError, match=f"config file {bad}: invalid YAML") as e:
        load(Outer, bad)
    assert "<unicode string>" not in str(e.value)
    with pytest.raises(ConfigError, match="--set value 'a: b: c' is not valid YAML"):
        load(Outer, None, ["x=a: b: c"])
    # YAML 1.1 reads `on:` as a bool key: an unknown-key error, not a TypeError while sorting the keys
    mixed = tmp_path / "mixed.yaml"
    mixed.write_text("on: 1\nzz_typo: 2\n")
    with pytest.raises(ConfigError, match="unknown config key"):
        load(Outer, mixed)


def test_yaml_tags_are_refused_not_run(tmp_path):
    """A config naming a Python object (`!!python/object/apply:os.system`) is invalid YAML, nothing runs."""
    from resim.config import ConfigError, load

    marker = tmp_path / "ran"
    cfg = tmp_path / "evil.yaml"
    cfg.write_text(f"steps: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(ConfigError, match="evil.yaml: invalid YAML"):
        load(Inner, cfg)
    assert not marker.exists()


def test_a_yaml_bomb_is_refused_before_it_expands(tmp_path):
    """478 bytes of nested aliases ("billion laughs") used to grow past 3 GB when the config was copied."""
    from resim.config import ConfigError, load

    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 9):
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [" + ",".join([f"*{prev}"] * 9) + "]")
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match="bomb.yaml: invalid YAML.*expand"):
        load(Inner, bomb)
    from resim.config import safe_yaml
    assert safe_yaml("x: &v 3.0\ny: *v\n") == {"x": 3.0, "y": 3.0}     # a handful of aliases is fine
