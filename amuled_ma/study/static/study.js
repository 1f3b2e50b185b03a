// The participant page of an amuled study (jsPsych 7: html-button-response for the consent,
// survey-html-form for the questions). Every answer is posted at once; the page can be left
// and reopened: the id and token stay in this browser's localStorage, and the server gives
// only the items not answered yet.
//
// A pair: which of two decisions is the more morally acceptable, and how acceptable each one
// is on the study's scale. An expert state: every action of the task, the panel's beliefs and
// stated reasons; per action, acceptable or not and which framework justifies it; how clear
// the panel's reasons are (not asked where no reason was recorded).
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

// Post an answer; the page's data attributes say what the server replied (tests read them).
function send(body) {
  const data = document.body.dataset;
  data.pending = String(Number(data.pending || 0) + 1);
  post("/api/answer", body)
    .then((r) => {
      data.last = `${body.item}:${r.status}`;
      if (r.status !== 200 && r.status !== 409) {
        data.refused = String(Number(data.refused || 0) + 1);
        document.getElementById("notice").textContent =
          `Your answer to question ${body.item} was not saved (${r.body.error}). ` +
          "Reload this page to answer it again.";
      }
    })
    .finally(() => { data.pending = String(Number(data.pending) - 1); });
}

function radios(name, values, labels) {
  return values.map((v, i) =>
    `<label class="point"><input type="radio" name="${name}" value="${escapeHtml(String(v))}" ` +
    `required><span>${escapeHtml(labels ? labels[i] : String(v))}</span></label>`).join("");
}

function percent(p) { return `${Math.round(100 * p)}%`; }

function stateHtml(item, number, total, openPrompt) {
  const prompt = item.prompt
    ? `<details class="prompt"${openPrompt ? " open" : ""}><summary>The situation in words</summary>` +
      `${escapeHtml(item.prompt)}</details>`
    : "";
  const legend = item.legend ? `<p class="legend">${escapeHtml(item.legend)}</p>` : "";
  return `<p class="progress">Question ${number} of ${total}</p>` +
    `<div class="state">${item.svg}</div>${legend}${prompt}`;
}

function pairTrial(me, item, number) {
  const ask = item.instruction
    ? `<p class="question attention">${escapeHtml(item.instruction)}</p>`
    : `<p class="question">${escapeHtml(me.question)}</p>`;
  const points = Array.from({ length: me.rating_points }, (_, i) => i + 1);
  const choice = item.options.map((o) =>
    `<label class="option"><input type="radio" name="choice" value="${o.label}" required>` +
    `<span>${o.label}: ${escapeHtml(o.action)}</span></label>`).join("");
  const rows = item.options.map((o) =>
    `<tr><th scope="row">${o.label}: ${escapeHtml(o.action)}</th>` +
    points.map((p) => `<td><input type="radio" name="rate-${o.label}" value="${p}" required ` +
      `aria-label="${o.label}: ${p}"></td>`).join("") + "</tr>").join("");
  const html =
    `<fieldset class="choice">${ask}${choice}</fieldset>` +
    `<fieldset class="ratings"><p class="question">${escapeHtml(me.rating_question)}</p>` +
    `<table class="scale"><tr><th></th>${points.map((p) => `<th>${p}</th>`).join("")}</tr>` +
    `<tr class="anchors"><th></th><td colspan="${Math.ceil(me.rating_points / 2)}" ` +
    `class="low">1: completely unacceptable</td><td colspan="${Math.floor(me.rating_points / 2)}" ` +
    `class="high">${me.rating_points}: completely acceptable</td></tr>` +
    `${rows}</table></fieldset>`;
  return {
    type: jsPsychSurveyHtmlForm,
    preamble: stateHtml(item, number, me.total, false),
    html: html,
    button_label: "Next",
    data: { item: item.id },
    on_load: () => mark("item", item.id),
    on_finish: (data) => {
      const r = data.response;
      send({ participant: me.participant, token: me.token, item: item.id, choice: r.choice,
        ms: data.rt, ratings: { A: Number(r["rate-A"]), B: Number(r["rate-B"]) } });
    },
  };
}

function panelHtml(me, item) {
  const titles = Object.fromEntries(me.frameworks);
  const panel = item.panel;
  if (!panel) {
    return `<div class="panel"><p class="noreason">No panel answered about this state: ` +
      `${escapeHtml(me.no_reason)}.</p></div>`;
  }
  const head = item.actions.map((a) => `<th>${escapeHtml(a)}</th>`).join("");
  const rows = panel.members.map((m) =>
    `<tr><th scope="row">${escapeHtml(titles[m.name] || m.name)}</th>` +
    m.belief.map((p) => `<td>${percent(p)}</td>`).join("") +
    `<td class="status">${m.status === "ok" ? "" : escapeHtml(m.status)}</td></tr>`).join("");
  const fused = `<tr class="fused"><th scope="row">fused belief</th>` +
    panel.fused.map((p) => `<td>${percent(p)}</td>`).join("") + "<td></td></tr>";
  const reasons = panel.members.map((m) =>
    `<dt>${escapeHtml(titles[m.name] || m.name)}</dt>` + (m.reason
      ? `<dd class="reason">${escapeHtml(m.reason)}</dd>`
      : `<dd class="noreason">${escapeHtml(me.no_reason)}</dd>`)).join("");
  return `<div class="panel"><p class="question">What the panel believed about the actions</p>` +
    `<table class="beliefs"><tr><th></th>${head}<th></th></tr>${rows}${fused}</table>` +
    `<p class="question">The reasons the panel stated</p><dl class="reasons">${reasons}</dl></div>`;
}

function expertTrial(me, item, number) {
  const options = me.frameworks.map(([name, title]) =>
    `<option value="${escapeHtml(name)}">${escapeHtml(title)}</option>`).join("");
  const rows = item.actions.map((a, i) =>
    `<tr><th scope="row">${escapeHtml(a)}</th>` +
    `<td>${radios(`ok-${i}`, ["yes", "no"])}</td>` +
    `<td><select name="fw-${i}" required aria-label="framework for ${escapeHtml(a)}">` +
    `<option value="">choose...</option>${options}</select></td></tr>`).join("");
  const points = Array.from({ length: me.clarity_points }, (_, i) => i + 1);
  const clarity = item.has_reasons
    ? `<fieldset class="clarity"><p class="question">How clear are the panel's reasons? ` +
      `(1 = not clear at all, ${me.clarity_points} = very clear)</p>` +
      `${radios("clarity", points)}</fieldset>`
    : `<p class="noreason">The panel's members left no reason for this state ` +
      `(${escapeHtml(me.no_reason)}): there is no clarity to rate.</p>`;
  const html =
    `<p class="question">For each action: is it morally acceptable here, and which moral ` +
    `framework justifies it?</p><table class="judge"><tr><th>action</th>` +
    `<th>acceptable?</th><th>framework that justifies it</th></tr>${rows}</table>${clarity}`;
  return {
    type: jsPsychSurveyHtmlForm,
    preamble: stateHtml(item, number, me.total, true) + panelHtml(me, item),
    html: html,
    button_label: "Next",
    data: { item: item.id },
    on_load: () => mark("item", item.id),
    on_finish: (data) => {
      const r = data.response;
      const actions = item.actions.map((_, i) =>
        ({ acceptable: r[`ok-${i}`] === "yes", framework: r[`fw-${i}`] }));
      send({ participant: me.participant, token: me.token, item: item.id, ms: data.rt,
        actions: actions, clarity: item.has_reasons ? Number(r.clarity) : null });
    },
  };
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
  document.body.dataset.mode = me.mode;
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
    number += 1;
    timeline.push(item.kind === "expert"
      ? expertTrial(me, item, number) : pairTrial(me, item, number));
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
