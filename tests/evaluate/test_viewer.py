"""amuled view: the page's data against the panel's own numbers, the page in a real browser.

The browser tests drive Debian's chromium and chromedriver (``/usr/bin/chromium``,
``/usr/bin/chromedriver``, installed by ``.ci/setup``) headless with selenium; they skip,
saying why, where either is missing. Screenshots and the measured figures go to
``$AMULED_ARTIFACTS`` when set (CI keeps that folder), else to the test's ``tmp_path``.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import statistics
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from scenario_feedback import make_feedback
from sparse_files import sparse
from tiny_cli import RULES, TINY

from amuled_ma.cli import main
from amuled_ma.evaluate import episode_trace as trace
from amuled_ma.evaluate import page_server, viewer
from amuled_ma.evaluate.readonly_feedback import ReadOnlyStore
from amuled_ma.experiments.run_folder import scenario_of_run
from amuled_ma.experiments.trained_variants import trained_variant
from amuled_ma.learn.policies import action_log_probs, load_policy
from amuled_ma.tasks import make_task

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
#: Targets: a 300-step Driving episode with five agents.
MAX_BYTES = 3_000_000
MAX_LOAD_S = 2.0


# ---------------------------------------------------------------------------------------
# Fixtures: real tiny runs, a real browser


@pytest.fixture(scope="module")
def findmilk_run(tmp_path_factory, recordings_dir) -> Path:
    """A tiny FindMilk run: base, fine-tunes on the rules panel, on a replay ('replay') and
    on the rule-based human (no panel)."""
    run = tmp_path_factory.mktemp("view") / "findmilk"
    common = ["findmilk", "--run-dir", str(run), *TINY]
    assert main(["train", *common, *RULES]) == 0
    assert main(["finetune", *common, *RULES]) == 0
    recording = recordings_dir / "findmilk-gpt-4o-mini.json"
    replay = ["--name", "replay", "--set", f'feedback.recording="{recording}"']
    assert main(["finetune", *common, *replay]) == 0
    assert main(["finetune", *common, "--feedback", "human:rules"]) == 0
    return run


@pytest.fixture(scope="module")
def browser():
    """Headless Debian chromium driven by selenium, with the performance log on."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.skip(
            f"no browser for the viewer tests: {', '.join(missing)} missing; install them "
            "with 'apt-get install chromium chromium-driver' (.ci/setup does)"
        )
    webdriver = pytest.importorskip(
        "selenium.webdriver", reason="selenium is not installed: pip install -e '.[test]'"
    )
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in (
        "--headless=new",
        "--no-sandbox",  # CI runs as root
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--no-first-run",
        "--window-size=1400,1400",
    ):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


def artifacts_dir(tmp_path: Path) -> Path:
    """``$AMULED_ARTIFACTS`` (kept by CI) or the test's own folder."""
    folder = Path(os.environ.get("AMULED_ARTIFACTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def open_page(driver, path: Path, fragment: str = "") -> None:
    driver.get(path.resolve().as_uri() + (f"#{fragment}" if fragment else ""))
    for _ in range(200):
        if driver.execute_script("return document.body.getAttribute('data-ready')") == "1":
            return
        time.sleep(0.02)
    raise AssertionError(f"the page {path} never finished its script")


def wait_for_step(section, step: int) -> None:
    for _ in range(200):
        if section.get_attribute("data-step") == str(step):
            return
        time.sleep(0.02)
    raise AssertionError(f"the page stays at step {section.get_attribute('data-step')}, not {step}")


def page_data(path: Path) -> dict:
    text = path.read_text(encoding="utf-8")
    found = re.search(
        r'<script type="application/json" id="amuled-data">(.*?)</script>', text, re.S
    )
    assert found, "no data block in the page"
    return json.loads(found.group(1))


def expected_episode(run: Path, variant: str, episode: int = 0):
    """The greedy evaluation episode computed here, independently of the viewer."""
    scenario = scenario_of_run(run)
    actor = load_policy(run / variant / "model_last.pt", scenario.ppo)
    base = load_policy(run / "base" / "model_last.pt", scenario.ppo)
    task = make_task(scenario.task, 1, shaping_coef=0.0, seed=scenario.evaluation.seed + episode)
    obs = torch.as_tensor(task.reset()).float()
    rows, prompt_vars, actions, base_actions = [], [], [], []
    with torch.inference_mode():
        for _ in range(task.max_steps):
            rows.append(obs[0].numpy().copy())
            prompt_vars.append(task.prompt_variables([0])[0])
            action = action_log_probs(actor, obs).argmax(-1)
            actions.append(int(action[0]))
            base_actions.append(int(action_log_probs(base, obs).argmax(-1)[0]))
            obs, _, term, trunc, _ = task.step(action)
            obs = torch.as_tensor(obs).float()
            if bool(term[0]) or bool(trunc[0]):
                break
    return scenario, np.stack(rows), prompt_vars, actions, base_actions


def panel_numbers(scenario, feedback_name: str, rows, prompt_vars, scratch: Path):
    """The panel's own answer for the states, on a scratch store (the run stays as it is)."""
    feedback = make_feedback(feedback_name, scenario, scratch)
    try:
        return feedback.panel.fused(rows, prompt_vars)
    finally:
        feedback.close()


# ---------------------------------------------------------------------------------------
# The page's data, no browser needed


def test_page_data_matches_the_panel_and_the_policies(findmilk_run, tmp_path):
    out = tmp_path / "view.html"
    assert main(["view", str(findmilk_run), "-o", str(out)]) == 0
    data = page_data(out)
    names = [v["name"] for v in data["variants"]]
    assert names == ["finetune-amuled", "finetune-human-rules", "finetune-replay"]
    assert (
        data["mode"] == "greedy" and data["seed"] == scenario_of_run(findmilk_run).evaluation.seed
    )
    scenario, rows, prompt_vars, actions, base_actions = expected_episode(
        findmilk_run, "finetune-amuled"
    )
    v = data["variants"][0]
    assert v["T"] == len(actions) and v["a"] == actions and v["b"] == base_actions
    assert len(v["frames"]) == v["T"] + 1 and v["kind"] == "panel"
    out_panel = panel_numbers(scenario, "amuled", rows, prompt_vars, tmp_path / "scratch")
    st = v["st"]
    for t in range(v["T"]):
        u = v["s"][t]
        np.testing.assert_allclose(st["b"][u], out_panel.beliefs[t], atol=6e-5)
        np.testing.assert_allclose(st["w"][u], out_panel.weights[t], atol=6e-5)
        np.testing.assert_allclose(st["f"][u], out_panel.fused[t], atol=6e-5)
        np.testing.assert_allclose(st["k"][u][0], out_panel.conflict[t], atol=6e-5)
        assert [v["statuses"][i] for i in st["s"][u]] == out_panel.statuses[t].tolist()
    # distinct states are stored once
    assert len(st["b"]) == len({(tuple(r), json.dumps(p, sort_keys=True)) for r, p in
                                zip(rows.tolist(), prompt_vars, strict=True)})  # fmt: skip


def test_a_feedback_without_panel_shows_its_belief_and_says_so(findmilk_run, tmp_path):
    from amuled_ma.tasks.human import human_belief

    out = tmp_path / "human.html"
    argv = ["view", str(findmilk_run), "--variant", "finetune-human-rules", "-o", str(out)]
    assert main(argv) == 0
    v = page_data(out)["variants"][0]
    assert v["kind"] == "belief" and "not a panel" in v["note"] and len(v["agents"]) == 1
    assert v["st"]["w"] is None and v["st"]["k"] is None
    _, rows, _, actions, base_actions = expected_episode(findmilk_run, "finetune-human-rules")
    assert v["a"] == actions and v["b"] == base_actions
    expected = human_belief("findmilk", rows)
    np.testing.assert_allclose([v["st"]["f"][u] for u in v["s"]], expected, atol=6e-5)
    np.testing.assert_allclose([v["st"]["b"][u][0] for u in v["s"]], expected, atol=6e-5)


def test_viewing_never_writes_to_the_runs_store(findmilk_run, tmp_path):
    store = findmilk_run / "beliefs.sqlite"
    before = store.read_bytes()
    rows_before = sum(1 for _ in ReadOnlyStore(store).store.iter_rows())
    # a sampled episode visits states training never asked about
    out = tmp_path / "v.html"
    assert (
        main(["view", str(findmilk_run), "--mode", "sampled", "--episode", "3", "-o", str(out)])
        == 0
    )
    assert sum(1 for _ in ReadOnlyStore(store).store.iter_rows()) == rows_before
    assert store.read_bytes() == before


def test_render_html_escapes_text_and_pins_its_script_and_style_by_hash():
    evil = "</script><script>alert(1)</script> & \u2028"
    data = {"title": "<b>t</b>", "subtitle": "", "footer": "", "actions": ["a"], "texts": [evil],
            "variants": []}  # fmt: skip
    page = viewer.render_html(data)
    assert page.count("<script") == 2 and "alert(1)</script>" not in page
    assert "<title>&lt;b&gt;t&lt;/b&gt;</title>" in page
    block = re.search(r'id="amuled-data">(.*?)</script>', page, re.S).group(1)
    assert json.loads(block)["texts"] == [evil]
    csp = re.search(r'http-equiv="Content-Security-Policy" content="([^"]+)"', page).group(1)
    assert "default-src 'none'" in csp and "unsafe" not in csp and "http" not in csp
    for tag in ("script", "style"):
        body = re.search(rf"<{tag}>(.*?)</{tag}>", page, re.S).group(1)
        digest = base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()
        assert f"{tag}-src 'sha256-{digest}'" in csp


def test_text_table_stores_each_text_once_and_cuts_long_ones():
    table = viewer.TextTable(limit=10)
    assert table.add(None) == -1 and table.add("") == -1
    assert table.add("same") == table.add("same") == 0
    index = table.add("x" * 25)
    assert table.texts[index].startswith("x" * 10) and "15 more characters" in table.texts[index]
    # a page's texts in all stay within a budget: each is cut to an equal share
    table = viewer.TextTable()
    for i in range(10):
        table.add(f"{i}" * 1000)
    assert not table.fit(10_000) and table.fit(5_000)
    assert all(t.startswith(str(i) * 500) and "500 more" in t for i, t in enumerate(table.texts))


def test_view_errors_name_the_run_and_the_variants(findmilk_run, tmp_path, capsys):
    assert main(["view", str(tmp_path / "nothing")]) == 1
    assert "not a run directory" in capsys.readouterr().err
    assert main(["view", str(findmilk_run), "--variant", "finetune-nope"]) == 1
    err = capsys.readouterr().err
    assert "finetune-nope" in err and "finetune-amuled" in err and "base" in err
    only_base = tmp_path / "base-only"
    (only_base / "base").mkdir(parents=True)
    for name in ("config.json",):
        (only_base / name).write_bytes((findmilk_run / name).read_bytes())
    (only_base / "base" / "model_last.pt").write_bytes(
        (findmilk_run / "base" / "model_last.pt").read_bytes()
    )
    assert main(["view", str(only_base)]) == 1
    assert "no fine-tuned variant" in capsys.readouterr().err
    # a base policy can still be shown when named: actions only, said so
    out = tmp_path / "base.html"
    assert main(["view", str(only_base), "--variant", "base", "-o", str(out)]) == 0
    entry = page_data(out)["variants"][0]
    assert entry["kind"] == "none" and "not fine-tuned" in entry["note"]


def test_serve_answers_the_page_on_localhost_only(findmilk_run, tmp_path, capsys):
    page = tmp_path / "p.html"
    page.write_text("<!DOCTYPE html><p>hello</p>")
    server = page_server.make_server(page)
    host, port = server.server_address[:2]
    assert host == "127.0.0.1"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as answer:
            assert answer.status == 200 and answer.read() == page.read_bytes()
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/../etc/passwd", timeout=10)
        assert info.value.code == 404
    finally:
        server.shutdown()
        server.server_close()
    # the command: bounded, prints the URL
    out = tmp_path / "v.html"
    argv = ["view", str(findmilk_run), "--variant", "finetune-amuled", "-o", str(out)]
    assert main([*argv, "--serve", "--serve-seconds", "0.3"]) == 0
    assert re.search(r"serving .* at http://127\.0\.0\.1:\d+/", capsys.readouterr().out)


# ---------------------------------------------------------------------------------------
# In a real browser


def bar_values(box) -> dict[str, float]:
    return {
        bar.get_attribute("data-action"): float(bar.get_attribute("data-value"))
        for bar in box.find_elements("css selector", ".bar")
    }


def check_step(section, t, out_panel, clusters, actions, base_actions, action_names):
    assert section.get_attribute("data-step") == str(t)
    for c, agent in enumerate(clusters):
        box = section.find_element("css selector", f'.agent[data-agent="{agent}"]')
        values = bar_values(box)
        expected = dict(zip(action_names, out_panel.beliefs[t, c].tolist(), strict=True))
        assert values == pytest.approx(expected, abs=6e-5), (t, agent)
        weight = float(box.find_element("css selector", ".weight").get_attribute("data-weight"))
        assert weight == pytest.approx(float(out_panel.weights[t, c]), abs=6e-5)
    fused = bar_values(section.find_element("css selector", ".card.fused"))
    assert fused == pytest.approx(
        dict(zip(action_names, out_panel.fused[t].tolist(), strict=True)), abs=6e-5
    )
    flag = section.find_element("css selector", ".flag-disagree")
    assert flag.is_displayed() == (actions[t] != base_actions[t])


def test_browser_steps_bars_flags_keys_and_screenshot(browser, findmilk_run, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    out = tmp_path / "view.html"
    assert main(["view", str(findmilk_run), "-o", str(out)]) == 0
    scenario, rows, prompt_vars, actions, base_actions = expected_episode(
        findmilk_run, "finetune-amuled"
    )
    out_panel = panel_numbers(scenario, "amuled", rows, prompt_vars, tmp_path / "scratch")
    clusters = list(scenario.feedback.clusters)
    names = ["up", "down", "left", "right"]
    open_page(browser, out)
    assert (
        browser.find_elements("css selector", "#variant-tabs button")[0].text == "finetune-amuled"
    )
    section = browser.find_element(
        "css selector", 'section.variant[data-variant="finetune-amuled"]'
    )
    assert section.is_displayed()
    ticks = section.find_elements("css selector", ".ticks .tick")
    assert len(ticks) == len(actions)  # one step element per env step
    flagged = [
        int(t.get_attribute("data-step")) for t in ticks if "disagree" in t.get_attribute("class")
    ]
    assert flagged == [t for t in range(len(actions)) if actions[t] != base_actions[t]]

    def press(key):
        ActionChains(browser).send_keys(key).perform()

    check_step(section, 0, out_panel, clusters, actions, base_actions, names)
    press(Keys.ARROW_RIGHT)
    check_step(section, 1, out_panel, clusters, actions, base_actions, names)
    press(Keys.ARROW_RIGHT)
    press(Keys.ARROW_LEFT)
    assert section.get_attribute("data-step") == "1"
    press(Keys.END)
    check_step(section, len(actions) - 1, out_panel, clusters, actions, base_actions, names)
    press(Keys.HOME)
    assert section.get_attribute("data-step") == "0"
    press(Keys.ARROW_LEFT)
    assert section.get_attribute("data-step") == "0"  # stays on the first step
    if flagged:  # the timeline jumps to a disagreement
        ticks[flagged[-1]].click()
        check_step(section, flagged[-1], out_panel, clusters, actions, base_actions, names)
        assert "current" in ticks[flagged[-1]].get_attribute("class")
    # the other variant's tab shows its own episode
    browser.find_element(
        "css selector", '#variant-tabs button[data-variant="finetune-replay"]'
    ).click()
    other = browser.find_element("css selector", 'section.variant[data-variant="finetune-replay"]')
    assert other.is_displayed() and not section.is_displayed()
    browser.find_element(
        "css selector", '#variant-tabs button[data-variant="finetune-amuled"]'
    ).click()
    press(Keys.ARROW_RIGHT)
    png = artifacts_dir(tmp_path) / "viewer-findmilk.png"
    assert browser.save_screenshot(str(png))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    print(f"viewer screenshot: {png}")


def test_browser_shows_replayed_reasoning_and_abstentions(
    browser, findmilk_run, recordings_dir, tmp_path
):
    from amuled_ma.beliefs.sources.replay import ReplaySource
    from amuled_ma.beliefs.types import BeliefRequest

    variant = findmilk_run / "finetune-replay"
    scenario = trained_variant(findmilk_run, variant).scenario
    actor = trace.load_actor(variant / "model_last.pt", scenario.ppo)
    path = recordings_dir / "findmilk-gpt-4o-mini.json"
    source = ReplaySource(path, miss_policy="uniform")
    clusters = list(scenario.feedback.clusters)
    found = None
    for k in range(20):  # the first sampled episode visiting a state whose reply was kept
        ep = trace.replay_episode(
            actor, scenario.task, scenario.evaluation, episode=k, mode="sampled"
        )
        for t in range(ep.length):
            for cluster in clusters:
                request = BeliefRequest("findmilk", cluster, tuple(ep.obs[t].tolist()),
                                        ep.action_names)  # fmt: skip
                answer = source.lookup(request)
                if not isinstance(answer, str) and answer[1]:
                    found = (k, t, cluster, answer[1], ep)
                    break
            if found:
                break
        if found:
            break
    assert found, "no sampled episode of 20 visits a recorded exchange"
    k, t, cluster, raw, ep = found
    out = tmp_path / "replay.html"
    argv = ["view", str(findmilk_run), "--variant", "finetune-replay", "--episode", str(k)]
    assert main([*argv, "--mode", "sampled", "-o", str(out)]) == 0
    open_page(browser, out, f"finetune-replay:{t}")
    section = browser.find_element(
        "css selector", 'section.variant[data-variant="finetune-replay"]'
    )
    wait_for_step(section, t)
    box = section.find_element("css selector", f'.agent[data-agent="{cluster}"]')
    assert box.find_element("css selector", "pre.raw").get_attribute("textContent") == raw
    # an agent the recording lacks abstains: its status is shown and its weight is 0
    out_panel = panel_numbers(scenario, "amuled", ep.obs[: ep.length], ep.prompt_vars,
                              tmp_path / "scratch")  # fmt: skip
    missed = [(s, c) for s in range(ep.length) for c in range(len(clusters))
              if out_panel.statuses[s, c] != "ok"]  # fmt: skip
    if missed:
        s, c = missed[0]
        open_page(browser, out, f"finetune-replay:{s}")  # same page: the hash moves it
        section = browser.find_element(
            "css selector", 'section.variant[data-variant="finetune-replay"]'
        )
        wait_for_step(section, s)
        box = section.find_element("css selector", f'.agent[data-agent="{clusters[c]}"]')
        assert box.get_attribute("data-status") == out_panel.statuses[s, c]
        assert "abstained" in box.get_attribute("class")
        assert float(box.find_element("css selector", ".weight").get_attribute("data-weight")) == 0


def test_browser_page_makes_no_network_request(browser, findmilk_run, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    out = tmp_path / "view.html"
    assert main(["view", str(findmilk_run), "-o", str(out)]) == 0
    browser.get_log("performance")  # drop what earlier pages logged
    browser.get_log("browser")
    open_page(browser, out)
    for key in (Keys.ARROW_RIGHT, Keys.END, Keys.HOME, "]"):
        ActionChains(browser).send_keys(key).perform()
    for tab in browser.find_elements("css selector", "#variant-tabs button"):
        tab.click()
    for detail in browser.find_elements("css selector", "section.variant:not([hidden]) details")[
        :4
    ]:
        detail.click()
    time.sleep(0.3)
    urls = []
    for entry in browser.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message.get("method") == "Network.requestWillBeSent":
            urls.append(message["params"]["request"]["url"])
    assert urls, "the performance log saw no request at all (not even the page itself)"
    outside = [u for u in urls if not u.startswith(("file:", "data:"))]
    assert outside == [], f"the page asked the network for {outside}"
    errors = [e for e in browser.get_log("browser") if e.get("level") == "SEVERE"]
    assert errors == [], errors  # a CSP violation (a script or style not hashed) shows here
    csp = browser.execute_script(
        "return document.querySelector('meta[http-equiv=\"Content-Security-Policy\"]').content"
    )
    assert csp.startswith("default-src 'none';")


def test_browser_driving_300_steps_five_agents_size_and_load(
    browser, tmp_path_factory, recordings_dir, tmp_path
):
    run = tmp_path_factory.mktemp("view-driving") / "driving"
    common = ["driving", "--run-dir", str(run), *TINY]
    recording = recordings_dir / "driving-llama-3_1-70b.json"
    assert main(["train", *common]) == 0
    assert main(["finetune", *common, "--set", f'feedback.recording="{recording}"']) == 0
    out = tmp_path / "driving.html"
    start = time.perf_counter()
    assert main(["view", str(run), "-o", str(out)]) == 0
    write_s = time.perf_counter() - start
    data = page_data(out)
    v = data["variants"][0]
    assert v["T"] == 300 and len(v["agents"]) == 5 and v["kind"] == "panel"
    size = out.stat().st_size
    loads = []
    for _ in range(3):
        open_page(browser, out)
        loads.append(browser.execute_script(
            "var n = performance.getEntriesByType('navigation')[0];"
            "return n ? n.loadEventEnd - n.startTime"
            " : performance.timing.loadEventEnd - performance.timing.navigationStart;"
        ) / 1000.0)  # fmt: skip
    section = browser.find_element("css selector", "section.variant")
    ticks = section.find_elements("css selector", ".ticks .tick")
    assert len(ticks) == 300
    assert len(section.find_elements("css selector", ".agent[data-agent]")) == 5
    # the disagreements flagged are the ones computed here, and a flagged step says so
    *_, actions, base_actions = expected_episode(run, "finetune-amuled")
    flagged = [i for i, t in enumerate(ticks) if "disagree" in t.get_attribute("class")]
    assert flagged == [t for t in range(300) if actions[t] != base_actions[t]]
    for t in flagged[:1] + [i for i in range(300) if i not in flagged][:1]:
        ticks[t].click()
        wait_for_step(section, t)
        flag = section.find_element("css selector", ".flag-disagree")
        assert flag.is_displayed() == (t in flagged)
    load = statistics.median(loads)
    figures = {
        "file_bytes": size,
        "load_s_median_of_3": round(load, 3),
        "load_s_each": [round(x, 3) for x in loads],
        "distinct_states": v["distinct_states"],
        "texts": len(data["texts"]),
        "write_s": round(write_s, 2),
    }
    folder = artifacts_dir(tmp_path)
    (folder / "viewer-driving-figures.json").write_text(json.dumps(figures, indent=1))
    browser.save_screenshot(str(folder / "viewer-driving.png"))
    print(f"viewer driving episode (300 steps, 5 agents): {figures}")
    assert size < MAX_BYTES, figures
    assert load < MAX_LOAD_S, figures


def test_a_page_over_64_mib_is_refused_unread_before_serving(tmp_path):
    from amuled_ma.errors import AmuledError

    assert page_server.MAX_PAGE_BYTES == 64 * 2**20
    page = tmp_path / "p.html"
    sparse(page, 10 * 2**30)
    start = time.perf_counter()
    with pytest.raises(AmuledError) as info:
        page_server.make_server(page)
    assert time.perf_counter() - start < 1.0
    assert str(info.value) == (
        f"{page}: the page is 10,737,418,240 bytes, more than the 67,108,864 a page may be (a "
        "viewer page is at most a few MB); it is not read; is it the right file? Open it in "
        "a browser from the file instead (its file:// URL)"
    )
