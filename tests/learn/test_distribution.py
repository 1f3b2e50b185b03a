import torch
from torch.distributions import Categorical

from amuled_ma.learn.distribution import CategoricalDistribution


def make(logits):
    dist = CategoricalDistribution(logits.shape[-1])
    dist.update(logits)
    return dist


def test_log_prob_entropy_probs_match_torch():
    torch.manual_seed(0)
    logits = torch.randn(64, 5) * 3
    dist, ref = make(logits), Categorical(logits=logits)
    actions = ref.sample()
    one_hot = torch.nn.functional.one_hot(actions, 5).float()
    torch.testing.assert_close(dist.log_prob(one_hot), ref.log_prob(actions))
    torch.testing.assert_close(dist.entropy, ref.entropy())
    torch.testing.assert_close(dist.probs, ref.probs)
    torch.testing.assert_close(dist.mean, ref.probs)


def test_kl_matches_torch():
    torch.manual_seed(1)
    a, b = torch.randn(16, 4), torch.randn(16, 4)
    dist = CategoricalDistribution(4)
    dist.update(a)
    (pa,) = dist.params
    dist.update(b)
    (pb,) = dist.params
    expected = torch.distributions.kl_divergence(Categorical(logits=a), Categorical(logits=b))
    torch.testing.assert_close(dist.kl_divergence((pa,), (pb,)), expected)


def test_samples_are_one_hot_with_the_right_frequencies():
    torch.manual_seed(2)
    logits = torch.log(torch.tensor([[0.1, 0.2, 0.7]])).repeat(20000, 1)
    dist = make(logits)
    sample = dist.sample()
    assert sample.shape == (20000, 3)
    assert torch.all(sample.sum(-1) == 1) and set(sample.unique().tolist()) <= {0.0, 1.0}
    freq = sample.mean(0)
    torch.testing.assert_close(freq, torch.tensor([0.1, 0.2, 0.7]), atol=0.015, rtol=0)


def test_deterministic_output_is_argmax_one_hot():
    dist = CategoricalDistribution(3)
    out = dist.deterministic_output(torch.tensor([[0.0, 2.0, 1.0], [5.0, 0.0, 0.0]]))
    assert out.tolist() == [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
    module = dist.as_deterministic_output_module()
    assert module(torch.tensor([[0.0, 0.0, 3.0]])).tolist() == [[0.0, 0.0, 1.0]]


def test_std_is_bernoulli_std():
    dist = make(torch.log(torch.tensor([[0.25, 0.75]])))
    torch.testing.assert_close(dist.std, torch.tensor([[0.75**0.5 * 0.5, 0.75**0.5 * 0.5]]))


def test_plugs_into_rsl_rl_mlp_model_by_name():
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    obs = TensorDict({"policy": torch.zeros(3, 6)}, batch_size=[3])
    model = MLPModel(
        obs,
        {"actor": ["policy"]},
        "actor",
        4,
        hidden_dims=[8, 8],
        activation="tanh",
        distribution_cfg={"class_name": "amuled_ma.learn.distribution:CategoricalDistribution"},
    )
    actions = model(obs, stochastic_output=True)
    assert actions.shape == (3, 4)
    # CleanRL init: logits layer gain 0.01 -> near-uniform start
    torch.testing.assert_close(
        model.distribution.probs, torch.full((3, 4), 0.25), atol=0.01, rtol=0
    )
    assert model.get_output_log_prob(actions).shape == (3,)
