"""Feature networks: architecture checked against torchvision's published parameter counts
(they are written out here because torchvision cannot be installed beside our torch);
plumbing checked with random weights (real weights load from local files only)."""
import pytest
import torch

from resim.eval.inception import FID_FEATURE_DIM, FIDInception
from resim.eval.lpips import LPIPS


def _count(m):
    return sum(p.numel() for p in m.parameters())


def test_fid_inception_matches_torchvision_layout():
    torch.manual_seed(0)
    net = FIDInception()
    # torchvision inception_v3(aux_logits=False): 23,834,568 params, of which fc(2048->1000) = 2,049,000
    assert _count(net) == 23_834_568 - 2_049_000
    net.train()  # must stay in eval mode: FID is defined with BatchNorm running statistics
    assert not net.training
    feats = net(torch.rand(2, 3, 40, 64))
    assert feats.shape == (2, FID_FEATURE_DIM) and torch.isfinite(feats).all()


def test_fid_inception_refuses_wrong_weights(tmp_path):
    p = tmp_path / "bad.pth"
    torch.save({"foo": torch.zeros(1)}, p)
    with pytest.raises(ValueError, match="not an Inception-v3"):
        FIDInception.from_file(p)
    with pytest.raises(FileNotFoundError, match="docs/eval.md"):
        FIDInception.from_file(tmp_path / "missing.pth")


@pytest.mark.parametrize("net,trunk_params", [("vgg", 14_714_688), ("alex", 2_469_696)])
def test_lpips_layout_and_identity(net, trunk_params, tmp_path):
    torch.manual_seed(0)
    m = LPIPS(net)
    assert _count(m.features) == trunk_params  # torchvision vgg16 / alexnet `features`
    for i in range(5):  # placeholder heads are non-negative, as trained LPIPS heads are
        assert (getattr(m, f"lin{i}").model[1].weight >= 0).all()
    x = torch.rand(2, 3, 64, 64)
    assert torch.allclose(m(x, x), torch.zeros(2))
    d = m(x, torch.rand(2, 3, 64, 64))
    assert (d > 0).all()
    # round trip through the two-file loader in the real layouts
    trunk = {f"features.{k}": v for k, v in m.features.state_dict().items()}
    lin = {k: v for k, v in m.state_dict().items() if k.startswith("lin")}
    torch.save(trunk, tmp_path / "trunk.pth")
    torch.save(lin, tmp_path / "lin.pth")
    m2 = LPIPS.from_files(net, tmp_path / "trunk.pth", tmp_path / "lin.pth")
    y = torch.rand(2, 3, 64, 64)
    assert torch.allclose(m2(x, y), m(x, y))
    assert len(m2.weights_sha256) == 64


def test_i3d_shapes_and_state_dict_layout(tmp_path):
    from resim.eval.i3d import I3D

    torch.manual_seed(0)
    net = I3D("logits")
    keys = net.state_dict().keys()
    # key names of the pytorch-i3d port, so its Kinetics weights load as they are
    for k in ("Conv3d_1a_7x7.conv3d.weight", "Mixed_3b.b1b.bn.running_var", "Mixed_5c.b3b.conv3d.weight",
              "logits.conv3d.bias"):
        assert k in keys
    clip = torch.rand(1, 9, 3, 48, 64)
    assert net(clip).shape == (1, 400)
    torch.save(net.state_dict(), tmp_path / "i3d.pt")
    pool = I3D.from_file(tmp_path / "i3d.pt", feature_layer="pool")
    assert pool(clip).shape == (1, 1024)
