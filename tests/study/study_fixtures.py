"""Tiny trained runs for the study's tests, the real study server, and a headless browser.

- :func:`tiny_run`: a tiny FindMilk run (base, the rules panel, the rule-based human);
- :func:`reasoned_run`: a tiny FindMilk run fine-tuned on a copy of the authors' recording
  in which the states with the robot in the left column (``x = 0``) carry every member's
  reply with a stated reason (a JSON reply with ``reasoning``, as an Ollama member's), so a
  study of it has states with reasons and states without (:func:`fixture_reason` is the
  text of each);
- :func:`hand_study`: a one-item study folder written by hand (no run; for what the server
  does with the folder's files);
- :func:`start_server`: ``amuled study serve`` in its own process;
- :func:`browser`: Debian's headless chromium through selenium (skips with the reason when
  absent).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from tiny_cli import RULES, TINY

from amuled_ma.cli import main

ROOT = Path(__file__).parents[2]
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
#: The FindMilk actions, index = action id (the task's own names).
FINDMILK_ACTIONS = ("up", "down", "left", "right")


def tiny_run(folder: Path) -> Path:
    run = folder / "findmilk"
    common = ["findmilk", "--run-dir", str(run), *TINY]
    assert main(["train", *common, *RULES]) == 0
    assert main(["finetune", *common, *RULES]) == 0
    assert main(["finetune", *common, "--feedback", "human:rules"]) == 0
    return run


def fixture_reason(agent: str, obs: list[float], belief: list[float]) -> str:
    """The reason the fixture recording gives ``agent`` (the recording's name) in a state."""
    best = FINDMILK_ACTIONS[max(range(len(belief)), key=lambda a: belief[a])]
    x, y = int(obs[0]), int(obs[1])
    return (
        f"As the {agent} member, at ({x}, {y}) I favour moving {best}: it keeps the sleeping "
        f"baby at ({int(obs[6])}, {int(obs[7])}) asleep and still heads for the milk."
    )


def reasoned_recording(recordings_dir: Path, out: Path) -> Path:
    """The authors' FindMilk recording, with stated reasons where the robot has ``x = 0``."""
    data = json.loads((recordings_dir / "findmilk-gpt-4o-mini.json").read_text())
    for state in data["states"]:
        if state["obs"][0] != 0 or not state.get("beliefs"):
            continue
        state["exchanges"] = [
            {
                "agent": agent,
                "prompt": "(the state prompt)",
                "response": json.dumps(
                    {
                        "reasoning": fixture_reason(agent, state["obs"], belief),
                        **{name: p for name, p in zip(FINDMILK_ACTIONS, belief, strict=True)},
                    }
                ),
            }
            for agent, belief in state["beliefs"].items()
            if belief is not None
        ]
    path = out / "findmilk-reasons.json"
    path.write_text(json.dumps(data))
    return path


def reasoned_run(folder: Path, recordings_dir: Path) -> Path:
    run = folder / "findmilk-reasons"
    recording = reasoned_recording(recordings_dir, folder)
    common = ["findmilk", "--run-dir", str(run), *TINY]
    assert main(["train", *common]) == 0
    assert main(["finetune", *common, "--set", f'feedback.recording="{recording}"']) == 0
    return run


def hand_study(folder: Path) -> Path:
    """A study folder of one FindMilk pair, written by hand: ``study.json``, its picture
    and a consent page (what ``amuled study build`` writes, without a run)."""
    from amuled_ma.study.model import Item, Option, Study, write_study

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "states").mkdir(exist_ok=True)
    (folder / "states" / "q001.svg").write_text("<svg xmlns='http://www.w3.org/2000/svg'/>")
    (folder / "consent.html").write_text("<p>my own words</p>")
    options = (
        Option(label="A", variant="base", action=0, action_name="up"),
        Option(label="B", variant="amuled", action=1, action_name="down"),
    )
    item = Item(id="q001", kind="pair", run=0, task="findmilk", episode=0, step=0,
                met_by="base", obs=[0.0] * 8, prompt=None, picture="states/q001.svg",
                options=options)  # fmt: skip
    study = Study(seed=1, runs=["runs/findmilk"], variants=["base", "amuled"],
                  folders=[{"base": "base", "amuled": "finetune-amuled"}],
                  action_names={"findmilk": list(FINDMILK_ACTIONS)}, items=[item],
                  candidates=1)  # fmt: skip
    write_study(folder, study)
    return folder


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(study: Path, port: int) -> subprocess.Popen:
    """``amuled study serve STUDY --port PORT`` in its own process, once it answers.

    The built studies keep the template's consent page, so it is served with
    ``--allow-placeholder-consent``.
    """
    proc = subprocess.Popen(
        [sys.executable, "-m", "amuled_ma", "study", "serve", str(study), "--port", str(port),
         "--allow-placeholder-consent"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    for _ in range(300):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=1).status_code == 200:
                return proc
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise AssertionError(f"the server never answered: {proc.stderr.read().decode()[-2000:]}")


def browser(height: int = 1100):
    """A headless chromium (selenium); skips the test with the reason when there is none."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.skip(f"no browser: {', '.join(missing)} missing; apt-get install chromium "
                    "chromium-driver (.ci/setup does)")  # fmt: skip
    webdriver = pytest.importorskip("selenium.webdriver", reason="pip install -e '.[test]'")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size=1000,{height}"):  # fmt: skip
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


def wait_state(driver, wanted=("consent", "item", "done")) -> str:
    """Wait until the page marks one of the ``wanted`` states (``body[data-state]``)."""
    state = None
    for _ in range(400):
        state = driver.execute_script("return document.body.dataset.state")
        if state in wanted:
            return state
        time.sleep(0.025)
    raise AssertionError(f"page stuck in {state}")


def wait_sent(driver) -> None:
    """Wait until every answer the page posted has been answered by the server."""
    for _ in range(400):
        if driver.execute_script("return document.body.dataset.pending || '0'") == "0":
            return
        time.sleep(0.025)
    raise AssertionError("an answer was never answered by the server")


def agree_to_consent(driver) -> None:
    from selenium.webdriver.common.by import By

    driver.find_element(By.CSS_SELECTOR, "#jspsych-html-button-response-button-0 button").click()
    time.sleep(0.1)


def full_page_png(driver) -> bytes:
    """A screenshot of the whole page (the window grown to the page's height)."""
    height = driver.execute_script("return document.documentElement.scrollHeight")
    width = driver.get_window_size()["width"]
    driver.set_window_size(width, min(int(height) + 140, 4000))
    time.sleep(0.2)
    return driver.get_screenshot_as_png()


def artifacts(tmp_path: Path) -> Path:
    """``$AMULED_ARTIFACTS`` (kept by CI) or the test's own folder."""
    folder = Path(os.environ.get("AMULED_ARTIFACTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder
