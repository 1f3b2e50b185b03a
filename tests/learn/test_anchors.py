"""The KL anchor of the authors' recipe against a hand-computed 3-step example and PyTorch."""

import math

import pytest
import torch

from amuled_ma.learn.anchors import EpisodeWindowKL, per_sample_kl, window_kl

# probabilities of the taken action at steps 1..3, fine-tuned and base policy
P = [0.5, 0.25, 0.8]
Q = [0.4, 0.5, 0.6]


def _hand_kl(p: list[float], q: list[float]) -> float:
    """KL(q || p) of the two sequences normalised over time, written out by hand."""
    sp, sq = sum(p), sum(q)
    return sum((qi / sq) * math.log((qi / sq) / (pi / sp)) for pi, qi in zip(p, q, strict=True))


def test_three_steps_by_hand():
    window = EpisodeWindowKL(num_envs=1, capacity=8)
    window.start_iteration()
    got = [float(window.step(torch.tensor([math.log(p)]), torch.tensor([math.log(q)])))
           for p, q in zip(P, Q, strict=True)]  # fmt: skip
    # step 1: a window of one step: both log-softmaxes are [0], the KL is 0
    assert got[0] == 0.0
    # step 2: p = [2/3, 1/3], q = [4/9, 5/9]
    step2 = 4 / 9 * math.log((4 / 9) / (2 / 3)) + 5 / 9 * math.log((5 / 9) / (1 / 3))
    assert got[1] == pytest.approx(step2, rel=1e-6)
    assert got[1] == pytest.approx(0.103585, abs=1e-6)
    assert got[2] == pytest.approx(_hand_kl(P, Q), rel=1e-6)


def test_same_as_pytorch_kldivloss_on_the_authors_call():
    """``nn.KLDivLoss(reduction="sum", log_target=True)(log_softmax(ft), log_softmax(ref))``."""
    kl_loss = torch.nn.KLDivLoss(reduction="sum", log_target=True)
    logp = torch.log(torch.tensor(P))
    logq = torch.log(torch.tensor(Q))
    expected = kl_loss(torch.log_softmax(logp, 0), torch.log_softmax(logq, 0))
    mask = torch.ones(1, 3, dtype=torch.bool)
    got = window_kl(logp.double().unsqueeze(0), logq.double().unsqueeze(0), mask)
    assert float(got) == pytest.approx(float(expected), rel=1e-6)


def test_window_resets_at_episode_end_and_iteration_start():
    window = EpisodeWindowKL(num_envs=2, capacity=4)
    window.start_iteration()
    lp, lq = torch.log(torch.tensor(P)), torch.log(torch.tensor(Q))
    both = lambda k: (lp[k].repeat(2), lq[k].repeat(2))  # noqa: E731
    window.step(*both(0))
    window.end_episodes(torch.tensor([False, False]))
    second = window.step(*both(1))
    assert second[0] == second[1] and float(second[0]) > 0
    window.end_episodes(torch.tensor([True, False]))  # copy 0's episode ends at step 2
    third = window.step(*both(2))
    assert float(third[0]) == 0.0  # a new window: step 3 alone
    assert float(third[1]) == pytest.approx(_hand_kl(P, Q), rel=1e-6)
    window.start_iteration()  # the authors' lists are re-created every rollout
    assert float(window.step(*both(0))[1]) == 0.0


def test_window_cannot_outgrow_the_rollout():
    window = EpisodeWindowKL(num_envs=1, capacity=2)
    window.step(torch.zeros(1), torch.zeros(1))
    window.step(torch.zeros(1), torch.zeros(1))
    with pytest.raises(RuntimeError, match="start_iteration"):
        window.step(torch.zeros(1), torch.zeros(1))


def test_equation_anchor_is_the_log_ratio():
    logp, logq = torch.log(torch.tensor(P)), torch.log(torch.tensor(Q))
    assert torch.allclose(per_sample_kl(logp, logq), torch.log(torch.tensor(P) / torch.tensor(Q)))


def test_authors_recipe_fine_tune_trains_and_logs_its_anchor(tiny_scenario, factory, tmp_path):
    import numpy as np
    from lone_trainer import Trainer

    from amuled_ma.deliberation.feedback_base import CallableFeedback

    base = Trainer(tiny_scenario, tmp_path / "base", task_factory=factory).train()
    scenario = tiny_scenario.replace("finetune", recipe="authors", lambda_kl=1.0)
    feedback = CallableFeedback(
        lambda obs: np.tile([0.0, 0.0, 1.0, 0.0], (len(obs), 1)), name="left"
    )
    trainer = Trainer(
        scenario, tmp_path / "tune", variant="finetune:left", feedback=feedback,
        base_checkpoint=base.checkpoint, task_factory=factory,
    )  # fmt: skip
    assert trainer.alg.window is not None
    out = trainer.train()
    kls = [row["feedback/kl"] for row in out.curve]
    # a window-KL is never negative (a KL divergence), and the windows of several steps
    # give a positive one once the policy moves away from the base
    assert all(k >= 0 for k in kls) and any(k > 0 for k in kls)
    equation = Trainer(
        tiny_scenario, tmp_path / "eq", variant="finetune:left", feedback=feedback,
        base_checkpoint=base.checkpoint, task_factory=factory,
    )  # fmt: skip
    assert equation.alg.window is None
