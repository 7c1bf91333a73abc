"""Vid2World weight transfers: definitions, exactness on linear-in-time input, causality."""
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from resim.models.world.causalize import (CausalConv, CausalTemporalAttention, causal_kernel, causalize,
                                       extrapolation_coefficients)


def _conv3d(k=3, seed=0):
    torch.manual_seed(seed)
    return nn.Conv3d(3, 4, (k, 3, 3), padding=(k // 2, 1, 1), dtype=torch.float64)


def _conv1d(k=3, seed=0):
    torch.manual_seed(seed)
    return nn.Conv1d(3, 4, k, padding=k // 2, dtype=torch.float64)


def _causal_reference(x, w, b):
    """Direct definition: y[t] = Σ_i w'[i] x[t + i - (K-1)] with zero left padding (Conv3d layout)."""
    K = w.shape[2]
    xp = F.pad(x, (1, 1, 1, 1, K - 1, 0))
    return F.conv3d(xp, w, b)


def test_extrapolation_coefficients_closed_form():
    assert torch.allclose(extrapolation_coefficients(2, 1), torch.tensor([2.0, -1.0], dtype=torch.float64))
    # m = 3, j = 1: OLS over τ = 0, -1, -2 → x̂ = 4/3 x_t + 1/3 x_{t-1} - 2/3 x_{t-2}
    assert torch.allclose(extrapolation_coefficients(3, 1), torch.tensor([4 / 3, 1 / 3, -2 / 3], dtype=torch.float64))
    assert torch.allclose(extrapolation_coefficients(3, 2).sum(), torch.tensor(1.0, dtype=torch.float64))


@pytest.mark.parametrize("k", [3, 5])
def test_shift_and_masked_definitions(k):
    conv = _conv3d(k)
    w = conv.weight.detach()
    r = k // 2
    assert torch.equal(causal_kernel(w, "shift"), w)
    assert torch.equal(causal_kernel(w, "masked"), w[:, :, : r + 1])
    x = torch.randn(2, 3, 9, 5, 6, dtype=torch.float64)
    # masked: the causal layer equals the original layer with its future taps zeroed
    w0 = w.clone()
    w0[:, :, r + 1:] = 0
    ref = F.conv3d(x, w0, conv.bias, padding=(r, 1, 1))
    assert torch.allclose(causalize(conv, "masked")(x), ref, atol=1e-12)
    # shift: the original output delayed by r frames (the kernel moved r steps into the past)
    y = causalize(conv, "shift")(x)
    orig = conv(x)
    assert torch.allclose(y, _causal_reference(x, w, conv.bias), atol=1e-12)
    assert torch.allclose(y[:, :, k - 1:], orig[:, :, r: 9 - r], atol=1e-12)


@pytest.mark.parametrize("m", [2, 3])
@pytest.mark.parametrize("k", [3, 5])
def test_extrapolative_exact_on_linear_sequences(m, k):
    conv = _conv3d(k, seed=m)
    T = 12
    a, b = torch.randn(2, 3, 1, 5, 6, dtype=torch.float64), torch.randn(2, 3, 1, 5, 6, dtype=torch.float64)
    x = a + b * torch.arange(T, dtype=torch.float64)[None, None, :, None, None]
    causal = causalize(conv, "extrapolative", m=m)
    assert isinstance(causal, CausalConv) and causal.conv.weight.shape[2] == max(k // 2 + 1, m)
    y, ref = causal(x), conv(x)
    start, stop = causal.conv.weight.shape[2] - 1, T - k // 2   # away from the zero padding at both ends
    assert torch.allclose(y[:, :, start:stop], ref[:, :, start:stop], atol=1e-10)
    # on non-linear input it differs (the transfer is not a trivial identity)
    x2 = x + x ** 2 * 0.1
    assert (causal(x2)[:, :, start:stop] - conv(x2)[:, :, start:stop]).abs().max() > 1e-3


@pytest.mark.parametrize("m", [2, 3])
def test_extrapolative_conv1d(m):
    conv = _conv1d(3)
    x = torch.randn(2, 3, 1, dtype=torch.float64) + torch.randn(2, 3, 1, dtype=torch.float64) * torch.arange(10.0, dtype=torch.float64)
    y = causalize(conv, "extrapolative", m=m)(x)
    s = max(2, m) - 1
    assert torch.allclose(y[..., s:9], conv(x)[..., s:9], atol=1e-10)


@pytest.mark.parametrize("method", ["shift", "masked", "extrapolative"])
@pytest.mark.parametrize("layer", ["conv1d", "conv3d"])
def test_all_transfers_are_causal(method, layer):
    conv = _conv1d(5) if layer == "conv1d" else _conv3d(5)
    causal = causalize(conv, method, m=3)
    shape = (2, 3, 10) if layer == "conv1d" else (2, 3, 10, 4, 4)
    x = torch.randn(shape, dtype=torch.float64)
    y = causal(x)
    assert y.shape == conv(x).shape
    for f in range(9):
        x2 = x.clone()
        x2[:, :, f + 1:] = torch.randn_like(x2[:, :, f + 1:])
        assert torch.equal(causal(x2)[:, :, : f + 1], y[:, :, : f + 1])


def test_recursive_copy_and_attention():
    net = nn.Sequential(nn.Conv3d(3, 3, (1, 3, 3), padding=(0, 1, 1)), nn.Conv3d(3, 3, 3, padding=1), nn.ReLU())
    before = [p.clone() for p in net.parameters()]
    out = causalize(net, "masked")
    assert isinstance(out[1], CausalConv) and isinstance(out[0], nn.Conv3d)   # spatial-only conv untouched
    assert all(torch.equal(a, b) for a, b in zip(before, net.parameters()))   # pure: input unchanged
    attn = nn.MultiheadAttention(8, 2, batch_first=True)
    ca = causalize(attn)
    assert isinstance(ca, CausalTemporalAttention)
    x = torch.randn(2, 6, 8)
    y = ca(x, x, x)[0]
    x2 = x.clone()
    x2[:, 3:] += 1
    assert torch.allclose(ca(x2, x2, x2)[0][:, :3], y[:, :3], atol=1e-6)


def test_rejects_non_same_padding():
    with pytest.raises(ValueError, match="padding"):
        causalize(nn.Conv1d(2, 2, 3, padding=0))
