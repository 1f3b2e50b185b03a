"""The learner: PPO on rsl-rl with a categorical policy, base training and fine-tuning.

- :mod:`~amuled_ma.learn.distribution`: the categorical distribution plugged into rsl-rl.
- :mod:`~amuled_ma.learn.vecenv`: the bridge from batched tasks to rsl-rl's ``VecEnv``.
- :mod:`~amuled_ma.learn.config`: rsl-rl's config dict built from a scenario.
- :mod:`~amuled_ma.learn.population`: the training loop of every job (one job: a
  population of one), checkpoints.
"""
