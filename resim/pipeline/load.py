"""Loading a pipeline config: YAML + ``--set`` overrides → a validated ``PipelineConfig`` whose paths, model
folders, reused synthetic world and every reader's own options are checked before any work starts (each error
names its key). Apart from ``resim/pipeline/config.py`` because the reader checks build the readers, which import
the config's dataclasses."""
from __future__ import annotations

import json
from pathlib import Path

from resim.config import ConfigError, load, to_dict
from resim.folders import folder_problem
from resim.pipeline.config import PipelineConfig, absolute_paths
from resim.pipeline.sources.synth.generate import SynthConfig, preset
from resim.pipeline.units import make_reader, source_specs


def load_config(path: str | Path | None, overrides=(), out: str | Path | None = None) -> PipelineConfig:
    """YAML + ``--set`` overrides (+ ``--out``) → validated :class:`PipelineConfig`, paths made absolute
    (:func:`absolute_paths`; the YAML file itself is only read) and checked."""
    extra = list(overrides or ())
    if out is not None:
        extra.append(f"out={Path(out)}")
    cfg = absolute_paths(load(PipelineConfig, path, extra))
    check_paths(cfg)
    return cfg


def check_paths(cfg: PipelineConfig) -> None:
    """Existence checks, each naming its key, before any work starts."""
    if cfg.out is None:
        raise ConfigError("out: no output folder (set `out:` in the config or pass --out DIR)")
    for kind in ("opendv", "navsim", "carla"):
        root = getattr(cfg.sources, kind).root
        problem = folder_problem(root) if root is not None else None
        if problem:
            raise ConfigError(f"sources.{kind}.root: {root} {problem}")
    for key, p in (("encode.vae", cfg.encode.vae_path), ("encode.text_encoder", cfg.encode.text_encoder_path)):
        problem = folder_problem(p)
        if problem:
            raise ConfigError(f"{key}: {p} {problem} (a model folder is expected)")
        if not any((Path(p) / sub / "config.json").is_file() for sub in ("", "vae", "text_encoder")):
            raise ConfigError(f"{key}: {p} has no config.json (expected a diffusers/transformers folder)")
    check_synthetic_world(cfg)
    # Build every reader's own config now (cheap: no listing, no decoding), so a value only a reader
    # checks (e.g. `sources.navsim.split: synth/x`) fails here and in `resim pipeline check`, not at
    # enumerate time after OUT was prepared.
    for spec in source_specs(cfg):
        make_reader(spec)


def check_synthetic_world(cfg: PipelineConfig) -> None:
    """A synthetic world already in ``sources.synthetic.root`` must be the one the config describes.

    The world is reused when present (generating it again would overwrite it), and ``episodes``, ``seed``
    and ``preset`` are part of the dataset's config hash, so reusing a different world would label the
    data with a config that did not make it. Compared with the ``synth_config.json`` the generator writes.
    """
    s = cfg.sources.synthetic
    if s.root is None:
        return
    try:
        made_with = preset(s.preset, fork_fraction=s.fork_fraction, pace_fork_fraction=s.pace_fork_fraction)
    except ConfigError as e:
        raise ConfigError(f"sources.synthetic.preset: {e}") from None
    root = Path(s.root)
    if not (root / "ground_truth.json").exists():
        return                                  # generated on the first run (runner.ensure_synthetic)
    p = root / "synth_config.json"
    try:
        have = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"sources.synthetic.root: {root} holds a synthetic world without {p.name}, so it cannot "
                          "be checked against episodes/seed/preset; regenerate it (resim synth) or use "
                          "another root") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"sources.synthetic.root: {p} is unreadable ({type(e).__name__}: {e})") from None
    if not isinstance(have, dict):
        raise ConfigError(f"sources.synthetic.root: {p} is not a JSON object")
    want = json.loads(json.dumps({"episodes": s.episodes, "seed": s.seed, **to_dict(made_with)}))
    # a field the generator did not have yet when it wrote the file had its default's effect
    have = {**json.loads(json.dumps(to_dict(SynthConfig()))), **have}
    diff = [k for k in sorted(want) if have.get(k) != want[k]]
    if diff:
        raise ConfigError(
            f"sources.synthetic: the world in {root} was not made with this config's "
            "episodes/seed/preset/fork_fraction/pace_fork_fraction ("
            + ", ".join(f"{k}: {have.get(k)!r} on disk, {want[k]!r} by the config" for k in diff)
            + "); set sources.synthetic.episodes/seed/preset/fork_fraction/pace_fork_fraction to the world's values, "
              "or point sources.synthetic.root at a new folder (the world is generated there)")
