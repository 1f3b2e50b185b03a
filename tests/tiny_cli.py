"""Command-line settings of a tiny run (a few seconds), shared by the CLI-level tests."""

TINY = [
    "--set", "base.total_steps=1024",
    "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16",
    "--set", "finetune.iterations=3",
    "--set", "finetune.num_envs=4",
    "--set", "finetune.num_steps_per_env=8",
    "--set", "output.tensorboard=false",
    "--no-progress",
]  # fmt: skip
RULES = ["--set", 'feedback.source="rules"']
