"""Run the pipeline: enumerate → (skip committed units) → prompts → cut → label → balance → encode → write.

Two executors over the *same* stage classes:

* ``ray`` (default): Ray Data over work units; every stage is an actor pool
  (``compute=ActorPoolStrategy(size=ray.stages.<stage>.actors)``) with the CPUs/GPUs declared once in
  ``ray.stages``; the encode and prompt pools get a GPU each when the cluster has GPUs
  (``num_gpus: auto``). Starts an embedded local Ray when ``ray.address`` is null, joins a cluster
  otherwise (or reuses a Ray already initialised in this process).
* ``local``: a sequential loop, stage by stage, in this process (unit tests, debugging).

Rows are unit states (JSON strings of paths and labels); only the encode stage touches pixels at
training resolution, one clip-deep buffer at a time.
"""
from __future__ import annotations

import logging
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from resim.config import ConfigError, save
from resim.pipeline import curation, out_lock, quarantine, ray_connect, report, resume, stage_fit
from resim.pipeline.config import PipelineConfig, absolute_paths, to_dict
from resim.pipeline.dedup import dedup_dataset
from resim.pipeline.load import check_synthetic_world
from resim.pipeline.sources.episode import SourceError
from resim.pipeline.sources.synth.generate import generate, preset
from resim.pipeline.stages import UNIT_STAGES
from resim.pipeline.stages.base import OUTPUT_ERRNOS, Chain, OutputError
from resim.pipeline.stages.encode import data_config_hash
from resim.pipeline.stages.prompts import PromptStage, all_prompts
from resim.pipeline.submit import JOB_ENV, package_dirs
from resim.pipeline.units import OUTPUT_DIRS, dumps, loads, make_reader, new_state, source_specs
from resim.shards import split as dataset_split
from resim.shards.prompts import PromptTable
from resim.shards.schema import make_key, prompt_id

log = logging.getLogger("resim.pipeline")


class IncompleteRun(RuntimeError):
    """Units that ran without leaving a commit marker: the run must not report success (nothing is lost:
    committed units are kept and a rerun redoes the others)."""


def output_error(e: BaseException) -> OutputError | None:
    """The :class:`OutputError` behind ``e`` (Ray wraps a stage's exception in its own), or an ``OSError``
    of the driver's own writes that says OUT cannot be written, as one; ``None`` for anything else."""
    seen, first = set(), e
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OutputError):
            return OutputError(str(e))
        if isinstance(e, OSError) and e.errno in OUTPUT_ERRNOS:
            return OutputError(f"cannot write {e.filename or 'the output'}: {e.strerror}. Units committed so far "
                               "are kept; free the space (or fix the mount) and rerun the same command")
        e = getattr(e, "cause", None) or e.__cause__ or e.__context__
    # Ray Data passes a stage's exception to the driver as text only (UserCodeException keeps no cause)
    m = re.search(rf"{re.escape(OutputError.__module__)}\.OutputError: (.+)", str(first))
    return OutputError(m.group(1).strip()) if m else None


def check_committed(out: Path, todo: list[dict]) -> None:
    """Every unit this run ran must have its commit marker; otherwise fail, naming how many and one of them."""
    markers = resume.read_markers(out)
    missing = [s["unit_id"] for s in todo if s["unit_id"] not in markers]
    if missing:
        raise IncompleteRun(f"{len(missing)} of {len(todo)} units ran but did not commit (e.g. {missing[0]}); "
                            "the committed ones are kept: rerun the same command to complete the dataset")


@dataclass
class RunResult:
    out: Path
    stats: dict
    enumerated: int
    ran: int
    skipped: int
    wall_s: float
    report_png: Path | None = None
    extra: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------- enumerate
class EnumerateStage:
    """Stage 1: the configured sources → one initial state per item (driver side; listing is cheap).

    Listing follows the stages' rules (``stages/base.py``): a ``SourceError`` quarantines the source at once,
    an ``OSError`` (e.g. EIO reading a CARLA results file) is retried ``quarantine.max_attempts`` times
    first. Two items whose samples would get the same keys are refused here, before any unit runs
    (:func:`check_unique_keys`).
    """

    name = "enumerate"

    def __init__(self, cfg: PipelineConfig):
        self.cfg = cfg

    def __call__(self) -> tuple[list[dict], list[dict]]:
        states, bad = [], []
        for spec in source_specs(self.cfg):
            attempts = 0
            while True:
                attempts += 1
                reader = make_reader(spec)   # a ConfigError here is a config mistake: it propagates
                try:
                    items = reader.list_items()
                except SourceError as e:   # e.g. a missing NAVSIM split, an undecodable videos.csv: source unusable
                    bad.append(self._row(spec, spec.root, f"{e.item}: {e.reason}", attempts=attempts))
                    items = None
                except OSError as e:       # transient I/O: a fresh reader lists again, then the source is quarantined
                    if attempts < self.cfg.quarantine.max_attempts:
                        continue
                    bad.append(self._row(spec, spec.root, f"I/O error after {attempts} attempts: {e}",
                                         attempts=attempts))
                    items = None
                break
            if items is None:
                continue
            # Problems a reader found while listing that leave the source usable (CARLA: an unreadable
            # results file, whose routes then get no outcome) are quarantine rows too, never ignored;
            # `dropped`: that file alone is skipped, the source's units still run.
            for e in getattr(reader, "problems", ()):
                bad.append(self._row(spec, e.item, e.reason, status="dropped", attempts=attempts))
            if spec.max_items is not None:
                items = items[:spec.max_items]
            states.extend(new_state(spec, item) for item in items)
        check_unique_keys(states)
        ids = [s["unit_id"] for s in states]
        if len(set(ids)) != len(ids):
            raise RuntimeError("two work units share an id")   # our bug (unit ids hash origin + item id)
        return states, bad

    def _row(self, spec, item: str, reason: str, status: str = "quarantined", attempts: int = 1) -> dict:
        return {"item": str(item), "unit_id": f"_source-{spec.origin.replace('/', '-')}", "source": spec.origin,
                "stage": self.name, "status": status, "reason": reason, "attempts": attempts}


def check_unique_keys(states: list[dict]) -> None:
    """Refuse two units whose samples would share ``__key__``s; ``ConfigError`` naming both items.

    A sample's key is ``resim.shards.schema.make_key(source kind, item id, start frame)`` — the schema's key, which
    ``resim shards verify`` recomputes from ``meta.json`` — so it does not say which configured section an item
    came from. Two sections reading the same layout kind (``sources.opendv`` and the synthetic world's
    ``opendv`` layout, both holding ``synth/synth_0000.mp4``, e.g. because one points into the other) would
    write different units under identical keys. Unit ids (shard prefixes) differ, so only this check sees it.
    """
    seen: dict[tuple[str, str], dict] = {}
    clashes: list[tuple[dict, dict]] = []
    for st in states:
        k = (st["kind"], st["item_id"])
        if k in seen:
            clashes.append((seen[k], st))
        else:
            seen[k] = st
    if not clashes:
        return

    a, b = clashes[0]

    def where(st: dict) -> str:
        s = st["spec"]
        return f"{s['section']}" + (f" (layout {st['kind']})" if st["origin"] != st["kind"] else "") + \
            f" item {st['item_id']!r} under {s['root']}"

    more = f" ({len(clashes)} such pairs in all)" if len(clashes) > 1 else ""
    raise ConfigError(
        f"sources: {where(a)} and {where(b)} would write samples under the same keys "
        f"(make_key({a['kind']!r}, item_id, start_frame), e.g. {make_key(a['kind'], a['item_id'], 0)}){more}; "
        "the same data is configured twice, or two sources share relative paths: point one of them elsewhere, "
        "or leave the layout out of sources.synthetic.layouts")


def ensure_synthetic(cfg: PipelineConfig) -> None:
    """Generate the synthetic world into ``sources.synthetic.root`` unless one is already there."""
    s = cfg.sources.synthetic
    if s.root is None:
        return
    root = Path(s.root)
    if (root / "ground_truth.json").exists():
        check_synthetic_world(cfg)   # reused only if it is the world the config describes (ConfigError)
        return

    log.info("generating a synthetic world (%d episodes, seed %d, preset %s) in %s", s.episodes, s.seed,
             s.preset, root)
    generate(root, s.episodes, s.seed,
             preset(s.preset, fork_fraction=s.fork_fraction, pace_fork_fraction=s.pace_fork_fraction),
             overwrite=root.exists() and not any(root.iterdir()), progress=cfg.ray.progress_bars)


# ------------------------------------------------------------------------------------- executors
def is_embedded(cfg: PipelineConfig) -> bool:
    """This run's Ray is this machine alone: no ``ray.address``, not inside a Ray job (``RAY_ADDRESS``)."""
    return not cfg.ray.address and not os.environ.get("RAY_ADDRESS")


def init_ray(cfg: PipelineConfig) -> bool:
    """Start or join Ray; returns True when this call started it (and so should shut it down).

    A cluster that is absent, dead or of another Ray/Python version is a one-line ``ClusterError``
    (``resim.pipeline.ray_connect``)."""
    if is_embedded(cfg):
        ray_connect.secure_embedded()   # before `import ray`: Ray reads the mode at import
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    # after RAY_* are set; only the Ray executor needs ray (the local one runs without it)
    import ray

    if ray.is_initialized():
        return False
    kw = dict(include_dashboard=False, log_to_driver=True, logging_level=logging.ERROR,
              configure_logging=True)
    if cfg.ray.address:   # join a cluster from a checkout: ship our packages to its workers

        ray_connect.join(cfg.ray.address, logging_level=logging.ERROR,
                         runtime_env={"py_modules": package_dirs(), "excludes": ["__pycache__", "*.pyc"],
                                      "env_vars": dict(JOB_ENV)})
    elif os.environ.get("RAY_ADDRESS"):   # inside a Ray job (resim pipeline submit): the job's runtime env
        ray_connect.join(None, logging_level=logging.ERROR)
    else:
        # workers inherit this environment; make sure they can import our packages from the checkout
        repo = str(Path(__file__).resolve().parents[2])
        pp = os.environ.get("PYTHONPATH", "")
        if repo not in pp.split(os.pathsep):
            os.environ["PYTHONPATH"] = os.pathsep.join([repo] + ([pp] if pp else []))
        ray.init(num_cpus=cfg.ray.num_cpus, **kw)
    return True


def pool_names(cfg: PipelineConfig) -> list[str]:
    """The ``ray.stages`` entries a Ray run uses: its actor pools (``unit_pipeline``) and the prompt task."""
    fused = ("cut", "label", "balance") if cfg.ray.fuse_cpu_stages else ()
    return [n for n, _ in UNIT_STAGES if n not in fused or n == "label"] + ["prompts"]


def fit_to_cluster(cfg: PipelineConfig, have_gpu: bool) -> PipelineConfig:
    """``cfg`` with stage resources the connected Ray can schedule: clamped to the machine for an embedded run
    (one log line per clamped stage), else unchanged, or a one-line ``StageTooBig`` for a stage no node can run
    (``resim.pipeline.stage_fit``). Before any work: an impossible actor would otherwise wait forever."""
    nodes = stage_fit.cluster_nodes()
    names = pool_names(cfg)
    if is_embedded(cfg):
        machine = max(nodes, key=lambda n: (n.cpus, n.gpus, n.memory_bytes))   # one node: this machine
        # the prompt task is no pool: it ends on its own, so it need not fit beside them
        stages, notes = stage_fit.clamp_to_machine(cfg.ray.stages, names, have_gpu, machine,
                                                   pools=[n for n in names if n != "prompts"])
        for note in notes:
            log.warning("%s", note)
        return replace(cfg, ray=replace(cfg.ray, stages=stages))
    stage_fit.check_cluster([(n, stage_fit.request_of(getattr(cfg.ray.stages, n), have_gpu)) for n in names],
                            nodes, ray_connect.describe_address(cfg.ray.address))
    return cfg


def _quiet_ray_data(progress: bool) -> None:
    import ray.data   # see init_ray

    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False      # our own bar per stage (run_units_ray) instead
    ctx.print_on_execution_start = False
    for name in ("ray.data", "ray"):
        logging.getLogger(name).setLevel(logging.ERROR)
    # a stage's exception reaches the driver inside the one Ray Data raises (with the remote traceback);
    # Ray Data's own ERROR lines about it only repeat that, before the one-line error or the traceback we give
    logging.getLogger("ray.data").setLevel(logging.CRITICAL)


def start_prompts_ray(cfg: PipelineConfig, have_gpu: bool):
    """Encode the prompt table in a Ray task *while* the units run (it needs its own model load)."""
    import ray   # see init_ray

    res = cfg.ray.stages.prompts

    @ray.remote(num_cpus=res.num_cpus, num_gpus=stage_fit.resolve_gpus(res, have_gpu), memory=res.memory_bytes,
                max_retries=0)
    def encode_prompts(cfg_dict: dict) -> list[str]:
        texts = all_prompts()
        out = PromptStage(cfg_dict)({"text": [t for t, _ in texts], "role": [r for _, r in texts]})
        return list(out["prompt_id"])

    return encode_prompts.remote(to_dict(cfg))


def unit_pipeline(cfg: PipelineConfig) -> list[tuple[str, object, dict]]:
    """(pool name, callable class, constructor kwargs) in order; cut+label+balance fused when configured."""
    cfg_dict = to_dict(cfg)
    stages = list(UNIT_STAGES)
    if cfg.ray.fuse_cpu_stages:
        light = tuple(cls for name, cls in stages if name in ("cut", "label", "balance"))
        rest = [(n, c, {"cfg": cfg_dict}) for n, c in stages if n not in ("cut", "label", "balance")]
        return [("label", Chain, {"cfg": cfg_dict, "stages": light})] + rest
    return [(n, c, {"cfg": cfg_dict}) for n, c in stages]


class _Board:
    """Per-stage unit counters the stages bump (``mark.remote``); the driver polls them for its bars."""

    def __init__(self):
        self.counts: dict[str, int] = {}

    def mark(self, stage: str, n: int = 1) -> None:
        self.counts[stage] = self.counts.get(stage, 0) + n

    def get(self) -> dict[str, int]:
        return dict(self.counts)


def run_units_ray(cfg: PipelineConfig, states: list[dict], have_gpu: bool, on_done, progress: bool = True) -> None:
    import ray   # see init_ray

    if not states:
        return
    board = ray.remote(num_cpus=0)(_Board).remote() if progress else None
    # one block per unit up to a cap (blocks are the unit of scheduling; 88 k tiny blocks only cost overhead)
    ds = ray.data.from_items([{"unit": dumps(s)} for s in states], override_num_blocks=min(len(states), 8192))
    for name, cls, kwargs in unit_pipeline(cfg):
        res = getattr(cfg.ray.stages, name)
        ds = ds.map_batches(cls, fn_constructor_kwargs={**kwargs, "progress": board}, batch_size=1,
                            batch_format="numpy", compute=ray.data.ActorPoolStrategy(size=res.actors),
                            num_cpus=res.num_cpus, num_gpus=stage_fit.resolve_gpus(res, have_gpu),
                            memory=res.memory_bytes)
    if board is None:
        for row in ds.iter_rows():
            on_done(loads(row["unit"]))
        return
    # drain the dataset in a thread; draw one bar per stage here from the board's counters
    error: list[BaseException] = []

    def drain():
        try:
            for row in ds.iter_rows():
                on_done(loads(row["unit"]))
        except BaseException as e:  # noqa: BLE001 - re-raised in the main thread below
            error.append(e)

    t = threading.Thread(target=drain, daemon=True)
    t.start()
    bars = {name: tqdm(total=len(states), desc=f"{name:>8}", unit="unit", position=i, leave=True)
            for i, (name, _) in enumerate(UNIT_STAGES)}
    try:
        while t.is_alive():
            t.join(0.5)
            counts = ray.get(board.get.remote())
            for name, bar in bars.items():
                bar.update(counts.get(name, 0) - bar.n)
    finally:
        for bar in bars.values():
            bar.close()
        ray.kill(board)
    if error:
        raise error[0]


def run_prompts_local(cfg: PipelineConfig) -> list[str]:
    texts = all_prompts()
    out = PromptStage(cfg)({"text": [t for t, _ in texts], "role": [r for _, r in texts]})
    return list(out["prompt_id"])


def run_units_local(cfg: PipelineConfig, states: list[dict], on_done, progress: bool = True) -> None:
    for name, cls in UNIT_STAGES:
        stage = cls(cfg)
        states = [stage.run_one(s) for s in tqdm(states, desc=f"{name:>8}", disable=not progress, unit="unit")]
    for s in states:
        on_done(s)


# ------------------------------------------------------------------------------------------- run
def prepare_out(cfg: PipelineConfig, force: bool = False) -> Path:
    """Create OUT, refuse to mix two configs in one dataset, save the resolved config.

    OUT is bound to a config by its *committed* units, not by an earlier attempt. ``config_hash.txt`` is
    written here, before any work (so it exists whenever a marker does), but a different hash is refused
    only when OUT holds commit markers. A run that committed nothing (it failed on a config mistake found
    at run time, or crashed early) left only uncommitted leftovers, which a rerun would redo anyway: they
    are removed and OUT is re-stamped, so the corrected config is not refused as "a different config".
    Removing them matters: the prompt table and an uncommitted unit's shards would otherwise survive
    into the new config's dataset. (Stamping only at the first commit would need the Ray actors to
    coordinate; deriving the lock from the markers needs nothing.)
    """
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    stamp = out / "config_hash.txt"
    h = data_config_hash(cfg)
    old = stamp.read_text().strip() if stamp.exists() else None
    if old is not None and old != h:
        commits = out / "commits"
        committed = sum(1 for _ in commits.glob("*.json")) if commits.is_dir() else 0
        if committed and not force:
            raise ConfigError(f"out: {out} already holds a dataset made with a different config "
                              f"(data hash {old} != {h}, {committed} committed units); use another --out "
                              "(or --force)")
        if not committed:
            log.info("out: %s holds no committed unit of its earlier config (data hash %s); removing that "
                     "run's uncommitted leftovers and re-stamping it for %s", out, old, h)
            for sub in OUTPUT_DIRS:
                if (out / sub).is_dir():
                    shutil.rmtree(out / sub)
    save(cfg, out / "config.yaml")
    tmp = stamp.with_name(stamp.name + ".tmp")
    tmp.write_text(h + "\n")
    tmp.replace(stamp)
    return out


def run(cfg: PipelineConfig, *, force: bool = False, progress: bool | None = None) -> RunResult:
    """Run ``cfg`` into ``cfg.out`` holding its run lock (``resim.pipeline.out_lock``; ``OutBusy`` if another run
    holds it)."""
    t0 = time.perf_counter()
    cfg = absolute_paths(cfg)   # already so when loaded with load_config; workers get the same paths
    progress = cfg.ray.progress_bars if progress is None else progress
    Path(cfg.out).mkdir(parents=True, exist_ok=True)
    # Held from before prepare_out's data-hash check (which removes an uncommitted run's leftovers) to the
    # last stats file: a second run into OUT is refused at once (OutBusy), before it writes anything.
    with out_lock.hold(cfg.out):
        return _run_locked(cfg, force, progress, t0)


def prompts_complete(out: Path) -> bool:
    """Whether OUT's prompt table holds every prompt a dataset can reference."""
    if not (Path(out) / "prompts").is_dir():
        return False
    return {prompt_id(t) for t, _ in all_prompts()} <= set(PromptTable(Path(out)).ids())


def finished_listing(cfg: PipelineConfig) -> tuple[list[dict], list[dict]] | None:
    """The enumeration ``(states, bad sources)`` when OUT already holds this config's finished dataset (the
    same data hash, every enumerated unit committed, a complete prompt table), else None. It costs a listing and
    the markers, so the rerun of a finished run reports in seconds, without starting Ray; the listing is handed
    on, not made twice."""
    out = Path(cfg.out)
    stamp = out / "config_hash.txt"
    if not stamp.is_file() or stamp.read_text().strip() != data_config_hash(cfg) or not prompts_complete(out):
        return None
    s = cfg.sources.synthetic
    if s.root is not None and not (Path(s.root) / "ground_truth.json").exists():
        return None                 # the world is generated by the normal path
    states, bad = EnumerateStage(cfg)()
    todo, _ = resume.plan(states, resume.read_markers(out), cfg.quarantine.retry_quarantined)
    return None if todo else (states, bad)


def _run_locked(cfg: PipelineConfig, force: bool, progress: bool, t0: float) -> RunResult:
    started = False
    have_gpu, cpus = False, 1.0
    finished = finished_listing(cfg) if cfg.ray.executor == "ray" and not force else None
    if finished is not None:
        log.info("every unit of %s is committed for this config: nothing to run (Ray not started)", cfg.out)
        return _run_units(cfg, force, progress, t0, have_gpu, cpus, listing=finished)
    if cfg.ray.executor == "ray":
        # Ray first, checked against the stages before OUT is prepared: a cluster that cannot run the config is
        # one line and leaves OUT as it was (but for the run lock)
        started = init_ray(cfg)
    try:
        if cfg.ray.executor == "ray":
            import ray   # see init_ray

            have_gpu = ray.cluster_resources().get("GPU", 0) >= 1
            cpus = float(ray.cluster_resources().get("CPU", 1.0))
            cfg = fit_to_cluster(cfg, have_gpu)
        return _run_units(cfg, force, progress, t0, have_gpu, cpus)
    finally:
        if started:
            import ray   # see init_ray

            ray.shutdown()


def _run_units(cfg: PipelineConfig, force: bool, progress: bool, t0: float, have_gpu: bool,
               cpus: float, listing: tuple[list[dict], list[dict]] | None = None) -> RunResult:
    out = prepare_out(cfg, force)
    ensure_synthetic(cfg)
    states, bad_sources = listing if listing is not None else EnumerateStage(cfg)()
    quarantine.write_rows(out, "_enumerate", bad_sources)
    todo, skipped = resume.plan(states, resume.read_markers(out), cfg.quarantine.retry_quarantined)
    log.info("%d units enumerated, %d already committed, %d to run", len(states), len(skipped), len(todo))
    done = {"units": 0, "clips_written": 0}

    def on_done(summary: dict) -> None:   # the driver keeps counters only (markers hold the rest)
        done["units"] += 1
        done["clips_written"] += (summary.get("written") or {}).get("num_samples", 0)

    try:
        if not todo and prompts_complete(out):
            pass                    # a finished dataset: nothing to run, the stats below are recomputed
        elif cfg.ray.executor == "ray":
            import ray   # see init_ray

            _quiet_ray_data(progress)
            prompts = start_prompts_ray(cfg, have_gpu)
            run_units_ray(cfg, todo, have_gpu, on_done, progress)
            ray.get(prompts)
        else:
            run_prompts_local(cfg)
            run_units_local(cfg, todo, on_done, progress)
    except Exception as e:
        err = output_error(e)
        if err is None:
            raise
        raise err from None
    check_committed(out, todo)      # a unit that ran without committing is never counted as done
    dedup_s = 0.0
    if cfg.dedup.enabled:           # one pass over the whole dataset's signatures (resim/pipeline/dedup.py)

        t_dedup = time.perf_counter()
        dedup_dataset(out, cfg.dedup.max_bits, cfg.clip.num_frames, cfg.dedup.band_bits)
        dedup_s = time.perf_counter() - t_dedup

    # the train / held-out split over every committed episode (resim/shards/split.py): a rerun that adds
    # episodes rewrites it, and the hash rule keeps every earlier episode on its side
    split = dataset_split.write(out, cfg.split)
    staging = out / "_staging"
    if staging.is_dir() and not any(staging.iterdir()):
        staging.rmdir()
    sheet_s = 0.0
    if todo or not (out / "curation.png").is_file():    # dropped examples per reason (resim/pipeline/curation.py)
        t_sheet = time.perf_counter()
        curation.contact_sheet(out, cfg, states, quarantine.problems(quarantine.read_table(out)))
        sheet_s = time.perf_counter() - t_sheet
    wall = time.perf_counter() - t0
    markers = resume.read_markers(out)
    enumerated_ids = {s["unit_id"] for s in states}
    stats = report.compute_stats(out, [m for uid, m in markers.items() if uid in enumerated_ids],
                                 this_run={"units_run": len(todo), "units_skipped": len(skipped), "wall_s": wall,
                                           "executor": cfg.ray.executor,
                                           "clips_written": done["clips_written"], "dedup_s": round(dedup_s, 3),
                                           "curation_sheet_s": round(sheet_s, 3), "cpus": cpus},
                                 cfg=cfg)
    stats["split"] = split.summary()     # episodes on each side (OUT/split.json lists them)
    report.write_stats(out, stats)
    png = report.write_report_png(out, stats)
    return RunResult(out=out, stats=stats, enumerated=len(states), ran=len(todo), skipped=len(skipped),
                     wall_s=wall, report_png=png)

