"""Stage resources against the cluster before any work (resim/pipeline/stage_fit.py): a request no node can run is one
line on a cluster and clamped on an embedded run, which then finishes instead of waiting forever."""
import logging

import pytest

from resim.pipeline import runner
from resim.pipeline.config import StageResources, StagesResources
from resim.pipeline.stage_fit import NodeResources, Request, StageTooBig, check_cluster, clamp_to_machine

GIB = float(1 << 30)
LAPTOP = NodeResources(cpus=2, gpus=0, memory_bytes=4 * GIB)


def test_a_cluster_run_refuses_a_request_no_node_can_satisfy():
    with pytest.raises(StageTooBig) as e:
        check_cluster([("label", Request(1, 0, 0)), ("encode", Request(4, 0, 0))], [LAPTOP], "ray.address=auto")
    assert str(e.value) == (
        "ray.address=auto: ray.stages.encode asks 4 CPUs per actor, which the cluster can never run (no node has that "
        "many CPUs; cluster: 1 node: 2 CPUs + 0 GPUs + 4 GiB memory); lower ray.stages.encode.num_cpus or add a node "
        "that large")
    with pytest.raises(StageTooBig, match=r"ray.stages.encode asks 1 CPU \+ 1 GPU per actor.*no node has that many "
                                          r"GPUs.*lower ray.stages.encode.num_gpus"):
        check_cluster([("encode", Request(1, 1, 0))], [LAPTOP, LAPTOP], "ray.address=HEAD:6379")
    with pytest.raises(StageTooBig, match=r"asks 1 CPU \+ 8 GiB memory.*that much memory.*memory_gib"):
        check_cluster([("write", Request(1, 0, 8 * GIB))], [LAPTOP], "ray.address=auto")
    # CPUs on one node, the GPU on another: each exists, but no actor can have both
    with pytest.raises(StageTooBig, match="no single node has all of it at once"):
        check_cluster([("encode", Request(4, 1, 0))], [NodeResources(16, 0, GIB), NodeResources(2, 1, GIB)], "x")
    check_cluster([("encode", Request(2, 0, 4 * GIB))], [LAPTOP], "ray.address=auto")     # fits exactly: no error


def test_an_embedded_run_clamps_to_the_machine_and_says_so():
    stages = StagesResources(label=StageResources(2, 0.5), encode=StageResources(1, 4, 1),
                             write=StageResources(1, 0.25))
    got, notes = clamp_to_machine(stages, ["label", "encode", "write", "prompts"], False, LAPTOP,
                                  pools=["label", "encode", "write"])
    assert notes[0] == ("ray.stages.encode asks 4 CPUs + 1 GPU per actor, more than this machine's embedded Ray has "
                        "(2 CPUs + 0 GPUs + 4 GiB memory): using 2 CPUs, no GPU (this machine has none)")
    # one actor of each pool must fit at once (a waiting write actor would keep encode's CPUs): scaled together
    assert notes[1].startswith("ray.stages: one actor of each pool together asks more than this machine's embedded "
                               "Ray has (label 0.5 + encode 2 + write 0.25 = 2.75 CPUs > 2)")
    assert len(notes) == 2
    assert sum(getattr(got, n).num_cpus for n in ("label", "encode", "write")) <= 2
    assert got.encode.num_gpus == 0 and got.label.actors == 2
    assert clamp_to_machine(got, ["label", "encode", "write"], False, LAPTOP, ["label", "encode", "write"])[1] == []


# Before the clamp this run waited forever at encode 0/2. Clamping encode alone to 2 CPUs still hung (tried: the
# write actor kept 0.25 of the 2 CPUs while waiting for encode's output); the pools are scaled to fit together.
@pytest.mark.timeout(900)
@pytest.mark.slow   # a whole pipeline run
def test_an_embedded_run_asking_more_cpus_than_the_machine_is_clamped_and_finishes(ray_session, config_for, caplog):
    cfg = config_for("out", "sources.synthetic.layouts=[opendv]", "ray.stages.encode.num_cpus=4")
    assert ray_session.cluster_resources()["CPU"] == 2
    with caplog.at_level(logging.WARNING, logger="resim.pipeline"):
        res = runner.run(cfg)
    notes = [r.getMessage() for r in caplog.records if r.getMessage().startswith("ray.stages")]
    assert notes[0].startswith("ray.stages.encode asks 4 CPUs per actor, more than this machine's embedded Ray has "
                               "(2 CPUs + 0 GPUs"), notes
    assert notes[0].endswith("using 2 CPUs")
    assert notes[1].startswith("ray.stages: one actor of each pool together asks more than this machine's embedded "
                               "Ray has (label 0.5 + encode 2 + write 0.25 = 2.75 CPUs > 2)"), notes
    assert res.enumerated == 2 and res.stats["units"]["ok"] == 2 and res.stats["clips"]["total"] > 0
