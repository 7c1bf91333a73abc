"""The adversarial term of ``resim train vae``: a small spatio-temporal patch discriminator and hinge losses.

Why: an MSE (or L1) decoder returns the mean of what a latent could hold. On the synthetic world that is flat
grass, smeared lane dashes and tree blobs, and within a 4-frame latent group the moving edges ghost: the
optical-flow labeler then reads little of the ego motion off the reconstructions (docs/models/synth-vae.md,
"Limitations"). CogVideoX trains its VAE with a GAN loss besides L1 and LPIPS (Yang et al. 2024,
Sec. 2.1), as Stable Diffusion's and taming-transformers' autoencoders do; LPIPS needs downloaded VGG weights
and is left out, the discriminator is trained from scratch with the VAE.

The discriminator sees short stacks of frames (3D convolutions, 3 frames of temporal reach per layer) so it
can tell a sharp frame whose edges jump or ghost between frames from real motion, not only a blurred frame
from a sharp one. It is the PatchGAN of pix2pix / taming (a grid of real/fake logits, no pooling) in 3D, with
hinge losses as in taming's VQGAN.

One optimizer: the trainer owns a single AdamW over the model's parameters, so both players' losses are summed
into one scalar and kept apart by where their gradients can go (:func:`adversarial_losses`): the generator
term reaches the VAE only (the discriminator's weights are read detached), the discriminator term reaches the
discriminator only (the reconstruction is detached). One backward then gives each player exactly the gradient
of its own loss, as two optimizers would, in the same step.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.func import functional_call


class PatchDiscriminator3D(nn.Module):
    """Video ``(B, 3, T, H, W)`` in [-1, 1] → patch logits ``(B, 1, T', H', W')`` (real > 0, fake < 0).

    ``layers`` stride-2 spatial convolutions (kernel 3x4x4, temporal stride 1) from ``width`` channels up to
    ``4 * width``, GroupNorm and LeakyReLU(0.2) between them, then a 3x3x3 convolution to one logit per patch.
    """

    def __init__(self, width: int = 32, layers: int = 3, groups: int = 8):
        super().__init__()
        chans = [3] + [width * min(2 ** i, 4) for i in range(layers)]
        mods: list[nn.Module] = []
        for i, (cin, cout) in enumerate(zip(chans[:-1], chans[1:])):
            mods.append(nn.Conv3d(cin, cout, (3, 4, 4), stride=(1, 2, 2), padding=(1, 1, 1)))
            if i > 0:   # no normalisation on the first layer (pix2pix / DCGAN practice)
                mods.append(nn.GroupNorm(min(groups, cout), cout))
            mods.append(nn.LeakyReLU(0.2))
        mods.append(nn.Conv3d(chans[-1], 1, 3, padding=1))
        self.net = nn.Sequential(*mods)

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        return self.net(video)


def adversarial_losses(disc: nn.Module, real: torch.Tensor, fake: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(generator loss, discriminator loss) for one batch, hinge form (taming's VQGAN).

    ``real``/``fake``: ``(B, 3, T, H, W)`` in [-1, 1]; ``fake`` carries the VAE's graph. The generator loss
    ``-mean D(fake)`` back-propagates into ``fake`` only (the discriminator's parameters enter detached); the
    discriminator loss ``mean relu(1 - D(real)) + mean relu(1 + D(fake))`` into the discriminator only
    (``fake`` enters detached). Their sum can therefore go through one ``backward`` and one optimizer.
    """
    frozen = {k: v.detach() for k, v in disc.named_parameters()}
    frozen.update(dict(disc.named_buffers()))
    g_loss = -functional_call(disc, frozen, (fake,)).mean()
    d_loss = F.relu(1.0 - disc(real)).mean() + F.relu(1.0 + disc(fake.detach())).mean()
    return g_loss, d_loss
