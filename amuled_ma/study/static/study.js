// The participant page of an amuled study (jsPsych 7, html-button-response).
// Every answer is posted at once; the page can be left and reopened: the id and token stay
// in this browser's localStorage, and the server gives only the items not answered yet.
"use strict";

const KEY = "amuled-study";
const PARAMS = ["PROLIFIC_PID", "workerId", "participant"];

function saved() {
  try { return JSON.parse(localStorage.getItem(KEY) || "null"); } catch (e) { return null; }
}

async function post(path, body) {
  const response = await fetch(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
    keepalive: true,
  });
  return { status: response.status, body: await response.json() };
}

function escapeHtml(text) {
  const div = document.createElement("div");
  div.textContent = text;
  return div.innerHTML;
}

function mark(state, item) {
  document.body.dataset.state = state;
  document.body.dataset.item = item || "";
}

async function start() {
  const url = new URLSearchParams(window.location.search);
  let wanted = null, source = "assigned";
  for (const name of PARAMS) {
    if (url.get(name)) { wanted = url.get(name); source = name; break; }
  }
  const kept = saved();
  const request = {};
  if (kept && (!wanted || kept.participant === wanted)) {
    request.participant = kept.participant;
    request.token = kept.token;
  } else if (wanted) {
    request.participant = wanted;
    request.source = source;
  }
  const session = await post("/api/session", request);
  if (session.status !== 200) {
    document.getElementById("study").textContent = "This link cannot be used: " + session.body.error;
    mark("refused");
    return;
  }
  const me = session.body;
  localStorage.setItem(KEY, JSON.stringify({ participant: me.participant, token: me.token,
    consented: kept && kept.participant === me.participant && kept.consented }));
  document.body.dataset.participant = me.participant;
  const jsPsych = initJsPsych({
    display_element: "study",
    on_finish: () => {
      document.getElementById("study").innerHTML =
        "<p>Thank you: all your answers are saved. You may close this page.</p>";
      mark("done");
    },
  });
  const timeline = [];
  const consented = (saved() || {}).consented || me.answered > 0;
  if (!consented) {
    const consentText = await (await fetch("/consent")).text();
    timeline.push({
      type: jsPsychHtmlButtonResponse,
      stimulus: consentText,
      choices: ["I agree", "I do not agree"],
      on_load: () => mark("consent"),
      on_finish: (data) => {
        if (data.response !== 0) {
          jsPsych.endExperiment("Thank you. You did not agree, so nothing is asked or recorded.");
          return;
        }
        const now = saved();
        now.consented = true;
        localStorage.setItem(KEY, JSON.stringify(now));
      },
    });
  }
  let number = me.answered;
  for (const item of me.items) {
    const ask = item.instruction
      ? `<p class="question attention">${escapeHtml(item.instruction)}</p>`
      : `<p class="question">${escapeHtml(me.question)}</p>`;
    const prompt = item.prompt
      ? `<details class="prompt"><summary>The situation in words</summary>${escapeHtml(item.prompt)}</details>`
      : "";
    const legend = item.legend ? `<p class="legend">${escapeHtml(item.legend)}</p>` : "";
    timeline.push({
      type: jsPsychHtmlButtonResponse,
      stimulus: `<p class="progress">Question ${++number} of ${me.total}</p>` +
        `<div class="state">${item.svg}</div>${legend}${ask}${prompt}`,
      choices: item.options.map((o) => `${o.label}: ${o.action}`),
      data: { item: item.id },
      on_load: () => mark("item", item.id),
      on_finish: (data) => {
        const choice = item.options[data.response].label;
        document.body.dataset.pending = String(Number(document.body.dataset.pending || 0) + 1);
        post("/api/answer", { participant: me.participant, token: me.token, item: item.id,
          choice: choice, ms: data.rt })
          .then((r) => { document.body.dataset.last = `${item.id}:${r.status}`; })
          .finally(() => {
            document.body.dataset.pending = String(Number(document.body.dataset.pending) - 1);
          });
      },
    });
  }
  if (timeline.length === 0) {
    document.getElementById("study").innerHTML =
      "<p>Thank you: you have answered every question.</p>";
    mark("done");
    return;
  }
  jsPsych.run(timeline);
}

start();
