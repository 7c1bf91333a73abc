"""Stage resources (``ray.stages``) against what the Ray cluster has, before any work starts.

Ray schedules an actor only on one node that has all it asks for at once. An actor asking for more than any node
has is never started: Ray logs one autoscaler line and the pool waits forever (``opendv.yaml`` run embedded on a
2-core machine sat at ``encode 0/6``: 4 CPUs per encode actor). So each stage's per-actor request is compared
with every node's resources first:

* a cluster run (``ray.address`` set, or a Ray job): a request no node can ever satisfy is a
  :class:`StageTooBig` naming the stage, what it asks and what the cluster has;
* an embedded local run (``ray.address: null``): the machine is all there is, so the request is clamped to it
  and a one-line note says so (a cluster config run on a laptop then runs, slower, instead of hanging); and
  one actor of every pool must fit beside the others (:func:`clamp_to_machine`), else they are scaled together.

Pure functions over :class:`NodeResources` (no Ray needed to test them); :func:`cluster_nodes` reads them
from a running Ray.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterable

from resim.pipeline.config import StageResources, StagesResources
from resim.pipeline.ray_connect import ClusterError

GIB = float(1 << 30)
_EPS = 1e-9


class StageTooBig(ClusterError):
    """A stage asks per actor for more than any node of the cluster has."""


@dataclass(frozen=True)
class NodeResources:
    cpus: float
    gpus: float
    memory_bytes: float


@dataclass(frozen=True)
class Request:
    """What one actor (or task) of a stage asks for, ``num_gpus: auto`` resolved."""

    cpus: float
    gpus: float
    memory_bytes: float


def resolve_gpus(res: StageResources, have_gpu: bool) -> float:
    """``num_gpus: auto`` is one GPU per actor where the cluster has GPUs, none elsewhere."""
    if res.num_gpus == "auto":
        return 1.0 if have_gpu else 0.0
    return float(res.num_gpus)


def request_of(res: StageResources, have_gpu: bool) -> Request:
    return Request(float(res.num_cpus), resolve_gpus(res, have_gpu), float(res.memory_gib) * GIB)


def cluster_nodes() -> list[NodeResources]:
    """The alive nodes of the Ray this process is connected to (``ray.nodes()``)."""
    import ray   # ray takes seconds to import: only once connected (the rest is pure arithmetic, tested without Ray)

    out = []
    for n in ray.nodes():
        if not n.get("Alive", n.get("alive", False)):
            continue
        r = n.get("Resources") or {}
        out.append(NodeResources(float(r.get("CPU", 0.0)), float(r.get("GPU", 0.0)), float(r.get("memory", 0.0))))
    return out


def _fits(req: Request, node: NodeResources) -> bool:
    return (req.cpus <= node.cpus + _EPS and req.gpus <= node.gpus + _EPS
            and req.memory_bytes <= node.memory_bytes + _EPS)


def _n(x: float, what: str) -> str:
    return f"{x:g} {what}{'' if x == 1 else 's'}"


def _ask(req: Request) -> str:
    parts = [_n(req.cpus, "CPU")]
    if req.gpus:
        parts.append(_n(req.gpus, "GPU"))
    if req.memory_bytes:
        parts.append(f"{req.memory_bytes / GIB:.3g} GiB memory")
    return " + ".join(parts)


def _node(n: NodeResources) -> str:
    return f"{_n(n.cpus, 'CPU')} + {_n(n.gpus, 'GPU')} + {n.memory_bytes / GIB:.3g} GiB memory"


def _have(nodes: list[NodeResources]) -> str:
    shapes = sorted({n for n in nodes}, key=lambda n: (-n.cpus, -n.gpus, -n.memory_bytes))
    count = _n(len(nodes), "node")
    if len(shapes) <= 4:
        return f"{count}: " + ", ".join(
            (f"{sum(1 for n in nodes if n == sh)} x " if sum(1 for n in nodes if n == sh) > 1 else "") + _node(sh)
            for sh in shapes)
    return (f"{count}, at most {_n(max(n.cpus for n in nodes), 'CPU')}, {_n(max(n.gpus for n in nodes), 'GPU')} and "
            f"{max(n.memory_bytes for n in nodes) / GIB:.3g} GiB memory per node")


def check_cluster(requests: Iterable[tuple[str, Request]], nodes: list[NodeResources], where: str) -> None:
    """``StageTooBig`` for the first stage whose per-actor request fits on no node (``where``: the cluster's
    address as the config names it)."""
    if not nodes:
        raise ClusterError(f"{where}: the cluster has no alive node")
    for stage, req in requests:
        if any(_fits(req, n) for n in nodes):
            continue
        short = [(what, key) for what, key, ok in (
            ("CPUs", "num_cpus", any(req.cpus <= n.cpus + _EPS for n in nodes)),
            ("GPUs", "num_gpus", any(req.gpus <= n.gpus + _EPS for n in nodes)),
            ("memory", "memory_gib", any(req.memory_bytes <= n.memory_bytes + _EPS for n in nodes))) if not ok]
        if short:
            lacks = "no node has " + " or ".join(("that much " if w == "memory" else "that many ") + w
                                                 for w, _ in short)
            keys = [k for _, k in short]
        else:   # every resource exists somewhere, just not on one node together (e.g. GPUs only on small nodes)
            lacks = "no single node has all of it at once"
            keys = [k for k, v in (("num_cpus", req.cpus), ("num_gpus", req.gpus), ("memory_gib", req.memory_bytes))
                    if v]
        raise StageTooBig(
            f"{where}: ray.stages.{stage} asks {_ask(req)} per actor, which the cluster can never run ({lacks}; "
            f"cluster: {_have(nodes)}); lower " + " / ".join(f"ray.stages.{stage}.{k}" for k in keys)
            + " or add a node that large")


def clamp_to_machine(stages: StagesResources, names: Iterable[str], have_gpu: bool, node: NodeResources,
                     pools: Iterable[str] = ()) -> tuple[StagesResources, list[str]]:
    """``stages`` fitted to this one machine (embedded runs: the machine is the whole cluster), with one line per
    change:

    1. each named stage's per-actor request is cut to what the machine has (an oversized actor waits forever);
    2. then, where one actor of every pool in ``pools`` together still asks more than the machine has, the pools'
       requests are scaled down together until they fit. A fixed-size Ray Data pool holds its actors until its
       input ends, so a downstream pool (write) waiting for input can keep the CPUs an upstream one (encode) needs
       to start: both wait forever. One actor of each at once always makes progress.
    """
    names, pools = list(names), list(pools)
    notes = []
    for stage in names:
        res: StageResources = getattr(stages, stage)
        req = request_of(res, have_gpu)
        new = {}
        if req.cpus > node.cpus + _EPS:
            new["num_cpus"] = node.cpus
        if req.gpus > node.gpus + _EPS:   # only an explicit count can exceed (auto is 1 where a GPU exists)
            new["num_gpus"] = node.gpus
        if req.memory_bytes > node.memory_bytes + _EPS:
            new["memory_gib"] = node.memory_bytes / GIB
        if not new:
            continue
        clamped = replace(res, **new)
        notes.append(f"ray.stages.{stage} asks {_ask(req)} per actor, more than this machine's embedded Ray has "
                     f"({_node(node)}): using "
                     f"{_ask(request_of(clamped, have_gpu))}"
                     + (", no GPU (this machine has none)" if "num_gpus" in new and node.gpus == 0 else ""))
        stages = replace(stages, **{stage: clamped})
    if pools:
        stages, note = _scale_pools_together(stages, pools, have_gpu, node)
        if note:
            notes.append(note)
    return stages, notes


def _floor4(x: float) -> float:
    # Ray keeps resource quantities to 1e-4; rounding down keeps the scaled sum within the machine
    return math.floor(x * 1e4) / 1e4


# (Request field, StageResources key, how a note names it, config units per Request unit)
_DIMENSIONS = (("cpus", "num_cpus", "CPUs", 1.0), ("gpus", "num_gpus", "GPUs", 1.0),
               ("memory_bytes", "memory_gib", "GiB memory", 1.0 / GIB))


def _scale_pools_together(stages: StagesResources, pools: list[str], have_gpu: bool,
                          node: NodeResources) -> tuple[StagesResources, str | None]:
    reqs = {p: request_of(getattr(stages, p), have_gpu) for p in pools}
    new: dict[str, dict] = {p: {} for p in pools}
    said = []
    for attr, key, unit, per in _DIMENSIONS:
        total, have = sum(getattr(r, attr) for r in reqs.values()), getattr(node, attr)
        if total <= have + _EPS:
            continue
        for p, r in reqs.items():
            if getattr(r, attr):
                new[p][key] = _floor4(getattr(r, attr) * have / total * per)
        parts = " + ".join(f"{p} {getattr(r, attr) * per:.4g}" for p, r in reqs.items() if getattr(r, attr))
        said.append(f"{parts} = {total * per:.4g} {unit} > {have * per:.4g}")
    if not said:
        return stages, None
    for p, changed in new.items():
        if changed:
            stages = replace(stages, **{p: replace(getattr(stages, p), **changed)})
    now = ", ".join(f"{p} {_ask(request_of(getattr(stages, p), have_gpu))}" for p in pools)
    return stages, (f"ray.stages: one actor of each pool together asks more than this machine's embedded Ray has "
                    f"({'; '.join(said)}), and a pool that cannot start beside the others would wait forever: "
                    f"scaled down to {now} per actor")
