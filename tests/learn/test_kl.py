import math

import torch

from amuled_ma.learn.anchors import per_sample_kl


def kl_reward(logp: torch.Tensor, logp_base: torch.Tensor, lam: float) -> torch.Tensor:
    # the anchor term of the reward, as AnchoredPPO subtracts it
    return -lam * per_sample_kl(logp, logp_base)


def test_kl_reward_hand_computed():
    # pi(a|s) = 0.5, pi_base(a|s) = 0.25: log(0.5) - log(0.25) = log 2
    logp = torch.log(torch.tensor([0.5, 0.25, 0.1]))
    logp_base = torch.log(torch.tensor([0.25, 0.25, 0.4]))
    out = kl_reward(logp, logp_base, 2.5)
    expected = torch.tensor([-2.5 * math.log(2.0), 0.0, -2.5 * math.log(0.25)])
    torch.testing.assert_close(out, expected)


def test_per_sample_kl_averages_to_closed_form_kl():
    torch.manual_seed(0)
    p = torch.tensor([0.6, 0.3, 0.1])
    q = torch.tensor([0.2, 0.5, 0.3])
    actions = torch.multinomial(p, 200_000, replacement=True)
    estimate = -kl_reward(p.log()[actions], q.log()[actions], 1.0).mean()
    closed = (p * (p / q).log()).sum()
    assert abs(float(estimate - closed)) < 0.01
    # the closed form is the same for every action, the per-sample term is not
    per_action = -kl_reward(p.log(), q.log(), 1.0)
    assert per_action.unique().numel() == 3


def test_kl_reward_zero_when_policies_agree():
    logp = torch.log(torch.tensor([0.3, 0.7]))
    assert torch.all(kl_reward(logp, logp.clone(), 2.5) == 0)
