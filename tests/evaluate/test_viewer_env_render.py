"""The deliberation env's own view of a step: the panel's beliefs under the task (ansi), or the
task's picture (rgb_array)."""

import numpy as np
import pytest

from amuled_ma.deliberation.env import DeliberationEnv
from amuled_ma.fusion import fuse


def test_ansi_render_prints_the_last_steps_beliefs_weights_and_fused_belief():
    env = DeliberationEnv("findmilk", render_mode="ansi", seed=0)
    env.reset(seed=0)
    assert env.render() == env.task.render_ansi(0)  # no step yet: the task only
    clusters = list(env.cluster_names)
    beliefs = np.array([[0.7, 0.1, 0.1, 0.1], [0.1, 0.1, 0.1, 0.7]] + [[0.25] * 4] * 3)
    actions = {"actor": 3, **{c: beliefs[i] for i, c in enumerate(clusters)}}
    _, _, _, _, infos = env.step(actions)
    text = env.render()
    assert text.startswith(env.task.render_ansi(0))
    diag = fuse(beliefs, "bjs-dst", return_diagnostics=True)
    assert f"last step: actor right, conflict K {diag.conflicts[0]:.3f}" in text
    rows = {line.split()[0]: line.split()[1:] for line in text.splitlines()[-6:]}
    for i, c in enumerate(clusters):
        values = [float(x) for x in rows[c]]
        np.testing.assert_allclose(values[:4], beliefs[i], atol=5e-4)
        assert values[4] == pytest.approx(infos["actor"]["weights"][c], abs=5e-4)
    np.testing.assert_allclose([float(x) for x in rows["fused"]], diag.fused, atol=5e-4)
    env.reset(seed=0)
    assert env.render() == env.task.render_ansi(0)  # a new episode forgets the last step


def test_rgb_render_is_the_tasks_picture_and_bad_modes_are_refused():
    env = DeliberationEnv("driving", render_mode="rgb_array", seed=0)
    env.reset(seed=0)
    image = env.render()
    assert image.dtype == np.uint8 and image.shape == (9 * 32, 5 * 32, 3)
    assert "rgb_array" in env.metadata["render_modes"]
    assert DeliberationEnv("driving").render() is None
    with pytest.raises(ValueError, match="rgb_array"):
        DeliberationEnv("driving", render_mode="human")
