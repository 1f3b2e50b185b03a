"""A study of a tiny trained Driving run: the pictures are Driving's road, the options its
actions; a few participants and an expert answer through the real server over HTTP."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import httpx
import pytest
from study_fixtures import free_port, start_server
from tiny_cli import RULES, TINY

from amuled_ma.cli import main
from amuled_ma.study.build import build_study

#: Driving's actions, index = action id (the authors' recording's "actions").
DRIVING_ACTIONS = ("straight", "right", "left")
LANES = 5


@pytest.fixture(scope="module")
def driving(tmp_path_factory) -> tuple[Path, Path, Path]:
    folder = tmp_path_factory.mktemp("driving-study")
    run = folder / "driving"
    common = ["driving", "--run-dir", str(run), *TINY]
    assert main(["train", *common, *RULES]) == 0
    assert main(["finetune", *common, *RULES]) == 0
    pairs = build_study([run], ["amuled", "base"], folder / "pairs", items=6, seed=1, episodes=1)
    assert len(pairs.items) == 7
    build_study([run], ["amuled", "base"], folder / "expert", items=3, seed=1, episodes=1,
                mode="expert")  # fmt: skip
    return run, folder / "pairs", folder / "expert"


def test_driving_pictures_are_the_road_and_options_its_actions(driving):
    _, pairs, _ = driving
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(pairs, port)
    sent = []
    try:
        for k in range(3):
            me = httpx.post(base + "/api/session", json={}).json()
            assert me["rating_points"] == 7
            for shown in me["items"][:3]:
                svg = shown["svg"]
                # the road: 5 lanes of 40 px, the car (dark) on the bottom row, in the lane
                # the observation's one-hot says (obs[6:11]), seen in the picture's title
                assert 'aria-label="Driving: your car in lane' in svg
                assert f'width="{LANES * 40}"' in svg and 'class="agent"' in svg
                assert svg.count('stroke-dasharray="8 8"') == LANES - 1  # lane markings
                assert "Orange-red: other cars" in shown["legend"]
                assert len(shown["options"]) == 2
                assert {o["action"] for o in shown["options"]} <= set(DRIVING_ACTIONS)
                choice = "AB"[k % 2]
                ratings = {"A": 1 + k, "B": 7 - k}
                form = {"participant": me["participant"], "token": me["token"],
                        "item": shown["id"], "choice": choice, "ms": 1200,
                        "ratings": ratings}  # fmt: skip
                assert httpx.post(base + "/api/answer", json=form).status_code == 200
                sent.append((me["participant"], shown["id"], choice, 1 + k, 7 - k))
    finally:
        server.kill()
        server.wait()
    db = sqlite3.connect(pairs / "answers.sqlite")
    rows = db.execute("SELECT participant, item, choice, rating_a, rating_b FROM answers")
    assert sorted(rows.fetchall()) == sorted(sent)
    db.close()


def test_driving_study_json_lane_and_actions_against_the_observation(driving):
    _, pairs, expert = driving
    study = json.loads((pairs / "study.json").read_text())
    assert study["action_names"] == {"driving": list(DRIVING_ACTIONS)}
    for item in study["items"]:
        lane = item["obs"][6:11].index(1.0)
        svg = (pairs / item["picture"]).read_text()
        assert f"your car in lane {lane} of {LANES}" in svg
        # the car is drawn in that lane: x = 40 * lane + 20 - 12
        assert f'class="agent" x="{40 * lane + 8}"' in svg
        for option in item["options"]:
            assert option["action_name"] == DRIVING_ACTIONS[option["action"]]

    # the expert page of a Driving state: its three actions; three judgements, not four
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(expert, port)
    try:
        me = httpx.post(base + "/api/session", json={}).json()
        shown = me["items"][0]
        assert shown["actions"] == list(DRIVING_ACTIONS)
        form = {"participant": me["participant"], "token": me["token"], "item": shown["id"],
                "ms": 3000, "clarity": None}  # fmt: skip
        four = [{"acceptable": True, "framework": "care"}] * 4
        assert httpx.post(base + "/api/answer", json={**form, "actions": four}).status_code == 400
        three = four[:3]
        assert httpx.post(base + "/api/answer", json={**form, "actions": three}).status_code == 200
    finally:
        server.kill()
        server.wait()
