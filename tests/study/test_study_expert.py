"""Expert mode: the numbers by hand, the study built with the panel's stated reasons, the
answers through the real server over HTTP (tampered forms refused and kept), the report."""

from __future__ import annotations

import csv
import io
import json
import math
import sqlite3
from collections import Counter
from pathlib import Path

import httpx
import pytest
from study_fixtures import (
    FINDMILK_ACTIONS,
    fixture_reason,
    free_port,
    reasoned_run,
    start_server,
)

from amuled_ma.study.analysis import (
    acceptability_values,
    acceptable_sets,
    agreement,
    answers_csv,
    clarity,
    framework_citations,
    framework_values,
    nominal_alpha,
    unreasoned_states,
)
from amuled_ma.study.answers import ExpertAnswer, Judgement, read_refusals
from amuled_ma.study.build import build_study
from amuled_ma.study.model import Item, PanelView, Study, StudyError, public_item, read_study
from amuled_ma.study.report import write_analysis

FRAMEWORKS = ["consequentialist", "deontological", "virtue", "care", "social_justice"]


def expert_item(item_id: str, panel: PanelView | None, policies: dict[str, int]) -> Item:
    return Item(id=item_id, kind="expert", run=0, task="findmilk", episode=0, step=0,
                met_by="amuled", obs=[0.0], prompt=None, picture=f"states/{item_id}.svg",
                policies=policies, panel=panel)  # fmt: skip


def judged(pid: str, item: str, oks: str, frameworks: list[str], clarity) -> ExpertAnswer:
    return ExpertAnswer(pid, item, clarity, tuple(
        Judgement(a, ok == "Y", fw) for a, (ok, fw) in enumerate(zip(oks, frameworks, strict=True))
    ), 1000.0, 0.0)  # fmt: skip


@pytest.fixture
def hand_study() -> tuple[Study, list[ExpertAnswer]]:
    panel = PanelView(
        feedback="amuled", agents=["care", "virtue"], rule="bjs-dst",
        beliefs=[[0.1, 0.6, 0.2, 0.1], [0.4, 0.4, 0.1, 0.1]], statuses=["ok", "ok"],
        fused=[0.3, 0.5, 0.1, 0.1], reasons=["Comfort the crying baby first.", None],
    )  # fmt: skip
    study = Study(
        mode="expert", seed=0, runs=["runs/fm"], variants=["amuled", "base"],
        folders=[{"amuled": "finetune-amuled", "base": "base"}],
        action_names={"findmilk": list(FINDMILK_ACTIONS)},
        frameworks=[(n, n.title()) for n in FRAMEWORKS], candidates=2,
        items=[expert_item("e1", panel, {"amuled": 1, "base": 3}),
               expert_item("e2", None, {"amuled": 0, "base": 2})],
    )  # fmt: skip
    answers = [
        judged("x1", "e1", "YYNN", ["care", "care", "none", "deontological"], 4),
        judged("x2", "e1", "YNNY", ["consequentialist", "none", "none", "care"], 2),
        judged("x3", "e1", "NYNN", ["none", "care", "none", "none"], 5),
        judged("x1", "e2", "YNYN", ["virtue", "none", "virtue", "none"], None),
        judged("x2", "e2", "YNNN", ["virtue", "none", "none", "none"], None),
    ]
    return study, answers


def test_expert_numbers_by_hand(hand_study):
    study, answers = hand_study
    # e1: up 2/3 and down 2/3 acceptable, left 0/3, right 1/3; e2: up 2/2, left 1/2 (not more
    # than half)
    sets = acceptable_sets(answers)
    assert sets == {"e1": (frozenset({0, 1}), 3), "e2": (frozenset({0}), 2)}
    agree = agreement(study, {k: v[0] for k, v in sets.items()})
    # care's top is down (in e1's set); virtue ties up and down (not counted); fused: down;
    # amuled takes down in e1, up in e2 (both acceptable); base right and left (neither)
    assert agree == {"cluster:care": [1, 1], "fused": [1, 1], "policy:amuled": [2, 2],
                     "policy:base": [0, 2]}  # fmt: skip
    cites = {c.framework: c for c in framework_citations(study, answers)}
    assert list(cites) == [*FRAMEWORKS, "none"]
    counted = {name: (c.cited, c.acceptable, c.by_action) for name, c in cites.items()}
    assert counted == {
        "consequentialist": (1, 1, {"up": 1}),
        "deontological": (1, 0, {"right": 1}),
        "virtue": (3, 3, {"left": 1, "up": 2}),
        "care": (4, 4, {"down": 2, "right": 1, "up": 1}),
        "social_justice": (0, 0, {}),
        "none": (11, 0, {"down": 3, "left": 4, "right": 3, "up": 1}),
    }
    assert cites["none"].share == pytest.approx(11 / 20)
    # clarity 4, 2, 5 by three experts: mean 11/3; with three experts the interval is the
    # lowest and highest expert's mean (each alone has probability 1/27 > 2.5%)
    clear = clarity(answers, seed=3)
    assert (clear.mean, clear.low, clear.high, clear.n) == (pytest.approx(11 / 3), 2.0, 5.0, 3)
    # Krippendorff's alpha of acceptable (1) / not (0) over 8 (state, action) units, by the
    # coincidence matrix: o11 = 4, o00 = 8, o01 = o10 = 4; n1 = 8, n0 = 12, n = 20;
    # alpha = 1 - (n - 1) (o01 + o10) / (2 n0 n1) = 1 - 19 * 8 / 192 = 5/24
    assert nominal_alpha(acceptability_values(answers)) == pytest.approx(5 / 24, abs=1e-12)
    # experts who always cite the same framework per unit agree perfectly
    same = [judged(p, "e1", "YYNN", ["care", "virtue", "none", "none"], 3) for p in ("a", "b")]
    assert nominal_alpha(framework_values(study, same)) == pytest.approx(1.0)
    assert unreasoned_states(study) == ["e2"]


@pytest.fixture(scope="module")
def reasoned(tmp_path_factory, recordings_dir) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("expert")
    run = reasoned_run(folder, recordings_dir)
    build_study([run], ["amuled", "base"], folder / "s", items=8, seed=3, mode="expert")
    return run, folder / "s"


def test_expert_study_shows_every_action_and_the_panel_s_reasons(reasoned, recordings_dir):
    _, folder = reasoned
    study = read_study(folder)
    assert study.mode == "expert" and len(study.items) == 8
    assert [name for name, _ in study.frameworks] == FRAMEWORKS
    recording = json.loads((recordings_dir / "findmilk-gpt-4o-mini.json").read_text())
    by_obs = {tuple(s["obs"]): s for s in recording["states"]}
    with_reasons = 0
    for item in study.items:
        assert item.kind == "expert" and item.options == ()
        assert item.panel is not None and item.panel.agents == FRAMEWORKS
        state = by_obs.get(tuple(item.obs))
        if item.obs[0] == 0 and state is not None:  # the fixture gave these states reasons
            expected = [
                fixture_reason(agent, state["obs"], state["beliefs"][agent])
                for agent in recording["clusters"]
            ]
            with_reasons += 1
        else:
            expected = [None] * 5
        assert item.panel.reasons == expected
        shown = public_item(item, "<svg/>", study.action_names["findmilk"])
        assert shown["actions"] == list(FINDMILK_ACTIONS)
        assert shown["has_reasons"] == (expected[0] is not None)
        assert [m["reason"] for m in shown["panel"]["members"]] == expected
        text = json.dumps(shown)
        assert "amuled" not in text and '"base"' not in text  # no variant reaches the page
    assert 0 < with_reasons < len(study.items)  # states with and without reasons


def test_expert_mode_refuses_attention_checks_and_needs_one_variant(reasoned, tmp_path):
    run, _ = reasoned
    with pytest.raises(StudyError, match="expert mode asks no attention checks"):
        build_study([run], ["amuled"], tmp_path / "x", items=2, seed=0, mode="expert",
                    attention=1)  # fmt: skip
    with pytest.raises(StudyError, match="at least two variants"):
        build_study([run], ["amuled"], tmp_path / "x", items=2, seed=0)
    study = build_study([run], ["amuled"], tmp_path / "one", items=3, seed=0, mode="expert")
    assert [i.kind for i in study.items] == ["expert"] * 3
    assert (tmp_path / "one" / "consent.html").read_text().count("framework") >= 1


def test_experts_over_http_tampered_forms_refused_and_the_report(reasoned):
    _, folder = reasoned
    study = read_study(folder)
    reasoned_ids = {i.id for i in study.items if i.panel is not None and i.panel.has_reasons()}
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(folder, port)
    posted: list[tuple[str, str, int, bool, str, int | None]] = []
    try:
        experts = []
        for k in range(3):
            me = httpx.post(base + "/api/session", json={}).json()
            assert me["mode"] == "expert" and me["clarity_points"] == 5
            assert [f[0] for f in me["frameworks"]] == [*FRAMEWORKS, "none"]
            experts.append(me)
            for shown in me["items"]:
                assert shown["actions"] == list(FINDMILK_ACTIONS)
                assert shown["has_reasons"] == (shown["id"] in reasoned_ids)
                number = int(shown["id"][1:])
                actions = [
                    {"acceptable": (a + number + k) % 3 != 0,
                     "framework": [*FRAMEWORKS, "none"][(a + k) % 6]}
                    for a in range(4)
                ]  # fmt: skip
                clarity = 1 + (number + k) % 5 if shown["has_reasons"] else None
                form = {"participant": me["participant"], "token": me["token"],
                        "item": shown["id"], "ms": 4000 + number, "actions": actions,
                        "clarity": clarity}  # fmt: skip
                r = httpx.post(base + "/api/answer", json=form)
                assert r.status_code == 200, r.text
                for a, j in enumerate(actions):
                    posted.append((me["participant"], shown["id"], a, j["acceptable"],
                                   j["framework"], clarity))  # fmt: skip

        me = experts[0]
        own = {"participant": me["participant"], "token": me["token"], "ms": 10}
        good = [{"acceptable": True, "framework": "care"}] * 4
        with_reason = sorted(reasoned_ids)[0]
        without = next(i.id for i in study.items if i.id not in reasoned_ids)
        # a fresh expert, so that only the tampering is refused, not a second answer
        fresh = httpx.post(base + "/api/session", json={}).json()
        new = {"participant": fresh["participant"], "token": fresh["token"], "ms": 10}
        tampered = [
            ({**new, "item": with_reason, "actions": good[:3], "clarity": 3},
             "expert: not one judgement per action"),
            ({**new, "item": with_reason, "actions": [*good[:3], {"acceptable": True,
              "framework": "utilitarianism"}], "clarity": 3}, "expert: unknown framework"),
            ({**new, "item": with_reason, "actions": [*good[:3], {"acceptable": "yes",
              "framework": "care"}], "clarity": 3}, "expert: acceptable not yes or no"),
            ({**new, "item": with_reason, "actions": good, "clarity": 6},
             "clarity outside the scale"),
            ({**new, "item": with_reason, "actions": good, "clarity": None},
             "clarity outside the scale"),
            ({**new, "item": without, "actions": good, "clarity": 2},
             "clarity without a stated reason"),
            ({**new, "item": without, "actions": good, "clarity": None, "ms": -1}, "bad time"),
        ]  # fmt: skip
        for form, _ in tampered:
            assert httpx.post(base + "/api/answer", json=form).status_code == 400
        again = {**own, "item": with_reason, "actions": good, "clarity": 3}
        assert httpx.post(base + "/api/answer", json=again).status_code == 409
        stranger = {**new, "token": me["token"], "item": without, "actions": good}
        assert httpx.post(base + "/api/answer", json=stranger).status_code == 403
        # resuming: nothing left for an expert who answered everything
        back = httpx.post(base + "/api/session", json={"participant": me["participant"],
                                                       "token": me["token"]}).json()  # fmt: skip
        assert back["items"] == [] and back["answered"] == 8
    finally:
        server.kill()
        server.wait()

    reasons = [r[3] for r in read_refusals(folder / "answers.sqlite")]
    for _, reason in tampered:
        assert reason in reasons
    assert "already answered" in reasons and "wrong token" in reasons
    db = sqlite3.connect(folder / "answers.sqlite")
    stored = db.execute(
        "SELECT a.participant, a.item, j.action, j.acceptable, j.framework, a.clarity "
        "FROM expert_answers a JOIN expert_actions j USING (participant, item)"
    ).fetchall()
    assert sorted((p, i, a, bool(ok), f, c) for p, i, a, ok, f, c in stored) == sorted(posted)
    assert db.execute("SELECT COUNT(*) FROM expert_answers").fetchone()[0] == 3 * 8
    db.close()

    # the report's numbers, counted here from what was posted
    write_analysis(folder)
    summary = json.loads((folder / "analysis" / "summary.json").read_text())
    assert summary["experts"] == 3 and summary["states_judged"] == 8
    assert summary["judgements"] == 3 * 8 * 4
    assert summary["states_without_reason"] == 8 - len(reasoned_ids)
    cited = Counter(f for *_, f, _ in posted)
    assert {c["framework"]: c["cited"] for c in summary["frameworks"]} == {
        f: cited[f] for f in [*FRAMEWORKS, "none"]
    }
    yes: Counter[tuple[str, int]] = Counter((i, a) for _, i, a, ok, _, _ in posted if ok)
    sets = {i: sorted(a for a in range(4) if 2 * yes[(i, a)] > 3) for i in {p[1] for p in posted}}
    assert {k: v["acceptable"] for k, v in summary["acceptable_sets"].items()} == sets
    policy = Counter()
    for item in study.items:
        for variant, action in item.policies.items():
            policy[variant] += action in sets[item.id]
    assert summary["agreement"]["policy:amuled"]["agree"] == policy["amuled"]
    assert summary["agreement"]["policy:base"]["agree"] == policy["base"]
    clarities = [c for (_, i, a, _, _, c) in posted if a == 0 and c is not None]
    assert summary["clarity"]["mean"] == pytest.approx(sum(clarities) / len(clarities))
    assert summary["clarity"]["ratings"] == 3 * len(reasoned_ids)
    assert not math.isnan(summary["alpha_acceptable"])
    report = (folder / "analysis" / "report.md").read_text()
    assert f"{8 - len(reasoned_ids)} of 8 states had no stated reason recorded" in report
    assert (folder / "analysis" / "expert.png").stat().st_size > 10_000
    rows = list(csv.DictReader(io.StringIO(answers_csv(folder))))
    assert len(rows) == 3 * 8 * 4
    assert {(r["participant"], r["item"], int(r["action"]), r["acceptable"] == "1",
             r["framework"]) for r in rows} == {p[:5] for p in posted}  # fmt: skip
