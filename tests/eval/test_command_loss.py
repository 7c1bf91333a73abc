"""`resim eval command-loss`: the command read off the model's own loss, on a model that uses the text and one
that does not."""
import numpy as np
import pytest
import torch

from resim.diffusion.schedule import alphas_cumprod
from resim.eval.command_loss import COMMANDS, clip_losses, command_loss_report, format_command_loss
from resim.eval.worldeval import EvalClip

AC = alphas_cumprod()
PATTERN = {c: float(k - 1) for k, c in enumerate(COMMANDS)}        # left -1, forward 0, right +1
TEXT = {c: torch.full((1, 2, 4), PATTERN[c]) for c in COMMANDS}
TEXT[None] = torch.full((1, 2, 4), 5.0)


def _clips(n=9, t_lat=5, h=2):
    """Clips whose future latents are their command's constant (left -1, forward 0, right +1), history zeros."""
    out = []
    for i in range(n):
        c = COMMANDS[i % 3]
        lat = np.zeros((t_lat, 2, 3, 3), np.float32)
        lat[h:] = PATTERN[c]
        out.append(EvalClip(f"k{i}", f"ep{i}", lat, np.zeros((1 + 4 * (t_lat - 1), 8, 8, 3), np.uint8), None, c,
                            1 + 4 * (h - 1), 10.0, False))
    return out


class Oracle(torch.nn.Module):
    """Predicts the exact v for the future the prompt names (x0 = the prompt's constant): loss 0 when told the truth."""

    def forward(self, x_t, t, text, traj, actions):
        x0 = text[:, 0, 0].view(-1, 1, 1, 1, 1).expand_as(x_t)
        a = AC[t].view(*t.shape, 1, 1, 1).to(x_t)
        noise = (x_t - a.sqrt() * x0) / (1 - a).sqrt()
        return a.sqrt() * noise - (1 - a).sqrt() * x0


class Blind(Oracle):
    """The same network with the text replaced by a constant: it cannot be told anything."""

    def forward(self, x_t, t, text, traj, actions):
        return super().forward(x_t, t, torch.full_like(text, 0.5), traj, actions)


def test_a_model_that_uses_the_command_is_read_right_and_a_blind_one_is_not():
    clips = _clips()
    recorded = [c.command for c in clips]
    text_for = TEXT.__getitem__
    good = command_loss_report(clip_losses(Oracle(), clips, text_for, AC, levels=(900, 300)), recorded, (900, 300))
    for r in good["levels"].values():
        assert r["accuracy"] == 1.0 and r["turn_sign_accuracy"] == 1.0
        assert r["worth_opposite"] > 1.0 and r["worth_null"] > 1.0
        assert r["confusion"] == [[3, 0, 0], [0, 3, 0], [0, 0, 3]]
    blind = command_loss_report(clip_losses(Blind(), clips, text_for, AC, levels=(900,)), recorded, (900,))
    r = blind["levels"]["900"]
    assert r["worth_opposite"] == pytest.approx(0.0, abs=1e-9) and r["worth_null"] == pytest.approx(0.0, abs=1e-9)
    assert r["turn_sign_accuracy"] == 0.0          # equal losses never count as the command being read
    assert "worth opposite" in format_command_loss(blind)


def test_history_is_clean_and_the_noise_is_shared_by_the_prompts():
    seen = []

    class Spy(Oracle):
        def forward(self, x_t, t, text, traj, actions):
            seen.append((x_t.clone(), t.clone()))
            return super().forward(x_t, t, text, traj, actions)

    clips = _clips(3)
    clip_losses(Spy(), clips, TEXT.__getitem__, AC, levels=(500,))
    assert len(seen) == 4                                           # one batch x 4 prompts
    assert all(torch.equal(x, seen[0][0]) for x, _ in seen)         # paired: the same noisy input
    t = seen[0][1]
    assert (t[:, :2] == 0).all() and (t[:, 2:] == 500).all()
    assert torch.equal(seen[0][0][:, :2], torch.zeros_like(seen[0][0][:, :2]))   # clean history (zeros here)


def test_levels_outside_the_schedule_are_refused():
    with pytest.raises(ValueError, match="noise levels"):
        clip_losses(Oracle(), _clips(3), TEXT.__getitem__, AC, levels=(1000,))


def test_counterfactual_clips_are_those_sharing_a_history_with_another_command():
    from resim.eval.command_loss import counterfactual_clips

    shared = _clips(6)                    # one (black) history under left / forward / right, twice
    shared[0].frames[-1] = 9              # futures differ: still one history
    shared[1].latents[0] += 0.5           # so do latents (posterior samples): still one history
    pair = _clips(2)                      # another history, under left and forward
    for c in pair:
        c.frames[0] = 1
    solo = _clips(1)                      # a history of its own: nothing to compare it with
    solo[0].frames[0] = 2
    idx, n = counterfactual_clips(shared + pair + solo)
    assert idx == list(range(8)) and n == 2
    twins = _clips(1) * 2                 # one history, one command: not counterfactual
    assert counterfactual_clips(twins) == ([], 0)
