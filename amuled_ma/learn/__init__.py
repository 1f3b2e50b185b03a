"""The learner: PPO on rsl-rl with a categorical policy, base training and fine-tuning."""
