"use strict";
// amuled view: one evaluation episode per variant, step by step. Everything this page
// shows is in the JSON block #amuled-data; it loads nothing and sends nothing.
(function () {
  var DATA = JSON.parse(document.getElementById("amuled-data").textContent);
  var SVG = "http://www.w3.org/2000/svg";
  var ACTIONS = DATA.actions;
  var TEXTS = DATA.texts;
  // the colours of the pictures: amuled_ma.tasks.colors.COLORS, the report's figures' table
  var C = DATA.colors || {};
  // the panel's answers and a distilled reward model's (amuled_ma.beliefs.types.FUSED_STATUSES)
  var ANSWERED = { ok: 1, repaired: 1, distilled: 1, distilled_miss: 1 };

  function el(tag, cls, text) {
    var node = document.createElement(tag);
    if (cls) node.className = cls;
    if (text !== undefined && text !== null) node.textContent = String(text);
    return node;
  }
  function svg(tag, attrs, text) {
    var node = document.createElementNS(SVG, tag);
    for (var key in attrs) node.setAttribute(key, attrs[key]);
    if (text !== undefined) node.textContent = text;
    return node;
  }
  function fmt(x, d) { return x === null || x === undefined ? "–" : Number(x).toFixed(d === undefined ? 3 : d); }
  function text(i) { return i === null || i === undefined || i < 0 ? null : TEXTS[i]; }
  function clear(node) { while (node.firstChild) node.removeChild(node.firstChild); }

  // ---------------------------------------------------------------- bars
  function bars(values, opts) {
    opts = opts || {};
    var grid = el("div", "bars " + (opts.cls || ""));
    for (var a = 0; a < ACTIONS.length; a++) {
      var v = values ? values[a] : null;
      var label = el("div", "label" + (opts.taken === a ? " taken" : ""), ACTIONS[a]);
      label.title = ACTIONS[a];
      var track = el("div", "track");
      var bar = el("div", "bar");
      bar.setAttribute("data-action", ACTIONS[a]);
      bar.setAttribute("data-value", v === null ? "" : String(v));
      bar.style.width = (v === null ? 0 : Math.max(0, Math.min(1, v)) * 100) + "%";
      track.appendChild(bar);
      grid.appendChild(label);
      grid.appendChild(track);
      grid.appendChild(el("div", "value", fmt(v)));
    }
    return grid;
  }

  // ---------------------------------------------------------------- pictures
  function findmilkPicture(v, t) {
    var lay = v.picture, n = lay.size, c = 40, pad = 4;
    var root = svg("svg", { width: n * c + 2 * pad, height: n * c + 2 * pad, role: "img",
      "aria-label": "FindMilk grid at step " + t });
    function cx(x) { return pad + x * c + c / 2; }
    function cy(y) { return pad + (n - 1 - y) * c + c / 2; }
    for (var i = 0; i <= n; i++) {
      root.appendChild(svg("line", { x1: pad + i * c, y1: pad, x2: pad + i * c, y2: pad + n * c, stroke: C.grid }));
      root.appendChild(svg("line", { x1: pad, y1: pad + i * c, x2: pad + n * c, y2: pad + i * c, stroke: C.grid }));
    }
    var visited = {};
    for (var s = 1; s <= t && s < v.frames.length; s++) visited[v.frames[s][0] + "," + v.frames[s][1]] = s;
    var m = lay.milk;
    root.appendChild(svg("rect", { x: cx(m[0]) - 15, y: cy(m[1]) - 15, width: 30, height: 30, rx: 5, fill: C.milk, stroke: C.ink, "stroke-width": 1.5, "class": "milk" }));
    root.appendChild(svg("text", { x: cx(m[0]), y: cy(m[1]) + 5, "text-anchor": "middle", fill: C.ink, "font-size": 13, "font-weight": 700 }, "M"));
    // a baby not reached yet: its kind's colour and letter; reached: solid good / bad with a white glyph
    var kinds = [["crying", C.crying, "C", "pacified", C.good, "✓"], ["sleeping", C.sleeping, "z", "woken", C.bad, "!"]];
    kinds.forEach(function (kind) {
      lay[kind[0]].forEach(function (p) {
        var gone = visited[p[0] + "," + p[1]] !== undefined;
        var g = svg("g", { "class": "baby " + kind[0] + (gone ? " " + kind[3] : "") });
        var fill = gone ? kind[4] : kind[1];
        g.appendChild(kind[0] === "crying"
          ? svg("circle", { cx: cx(p[0]), cy: cy(p[1]), r: 14, fill: fill, stroke: C.ink, "stroke-width": 1.5 })
          : svg("rect", { x: cx(p[0]) - 13, y: cy(p[1]) - 13, width: 26, height: 26, rx: 3, fill: fill, stroke: C.ink, "stroke-width": 1.5 }));
        g.appendChild(svg("text", { x: cx(p[0]), y: cy(p[1]) + (gone ? 6 : 4), "text-anchor": "middle",
          fill: gone ? "#fff" : C.ink, "font-size": gone ? 17 : 11, "font-weight": 700 }, gone ? kind[5] : kind[2]));
        var title = svg("title", {}, kind[0] + " baby at (" + p[0] + ", " + p[1] + ")" + (gone ? ", " + kind[3] + " at step " + (visited[p[0] + "," + p[1]] - 1) : ""));
        g.appendChild(title);
        root.appendChild(g);
      });
    });
    var pts = [];
    for (var j = 0; j <= t && j < v.frames.length; j++) pts.push(cx(v.frames[j][0]) + "," + cy(v.frames[j][1]));
    root.appendChild(svg("polyline", { points: pts.join(" "), fill: "none", stroke: C.path, "stroke-width": 3, "stroke-opacity": 0.7, "stroke-linejoin": "round" }));
    var r = v.frames[Math.min(t, v.frames.length - 1)];
    root.appendChild(svg("rect", { x: cx(r[0]) - 11, y: cy(r[1]) - 11, width: 22, height: 22, rx: 4, fill: C.agent, "class": "robot" }));
    if (t < v.T) {
      var moves = { up: [0, 1], down: [0, -1], left: [-1, 0], right: [1, 0] };
      var d = moves[ACTIONS[v.a[t]]];
      if (d) root.appendChild(svg("line", { x1: cx(r[0]), y1: cy(r[1]), x2: cx(r[0]) + d[0] * 26, y2: cy(r[1]) - d[1] * 26,
        stroke: C.path, "stroke-width": 4, "marker-end": "" }));
    }
    return root;
  }

  function drivingPicture(v, t) {
    var lanes = v.picture.lanes, far = v.picture.distance, w = 56, h = 32, pad = 4;
    var root = svg("svg", { width: lanes * w + 2 * pad + 24, height: (far + 1) * h + 2 * pad, role: "img",
      "aria-label": "Driving road at step " + t });
    function x(lane) { return pad + 24 + lane * w; }
    function y(d) { return pad + (far - d) * h; }
    root.appendChild(svg("rect", { x: x(0), y: pad, width: lanes * w, height: (far + 1) * h, fill: C.road }));
    for (var l = 1; l < lanes; l++)
      root.appendChild(svg("line", { x1: x(l), y1: pad, x2: x(l), y2: pad + (far + 1) * h, stroke: C.lane_mark, "stroke-dasharray": "8 8" }));
    for (var d = 0; d <= far; d++)
      root.appendChild(svg("text", { x: pad + 18, y: y(d) + h / 2 + 4, "text-anchor": "end", "font-size": 11, fill: C.muted }, String(d)));
    var f = v.frames[Math.min(t, v.frames.length - 1)];
    f[1].forEach(function (o) {
      var g = svg("g", { "class": "car" });
      g.appendChild(svg("rect", { x: x(o[0]) + 10, y: y(o[1]) + 4, width: w - 20, height: h - 8, rx: 4, fill: C.car }));
      g.appendChild(svg("title", {}, "car, lane " + o[0] + ", distance " + o[1]));
      root.appendChild(g);
    });
    f[2].forEach(function (o) {
      var g = svg("g", { "class": "grandma" });
      g.appendChild(svg("circle", { cx: x(o[0]) + w / 2, cy: y(o[1]) + h / 2, r: 10, fill: C.grandma, stroke: "#fff", "stroke-width": 2 }));
      g.appendChild(svg("title", {}, "grandma, lane " + o[0] + ", distance " + o[1]));
      root.appendChild(g);
    });
    var lane = f[0];
    root.appendChild(svg("rect", { x: x(lane) + 12, y: y(0) + 3, width: w - 24, height: h - 6, rx: 4, fill: C.agent, "class": "agent-car" }));
    if (t < v.T) {
      var act = ACTIONS[v.a[t]], to = lane + (act === "right" ? 1 : act === "left" ? -1 : 0);
      to = Math.max(0, Math.min(lanes - 1, to));
      root.appendChild(svg("line", { x1: x(lane) + w / 2, y1: y(0) + 2, x2: x(to) + w / 2, y2: y(1) + h / 2,
        stroke: C.policy, "stroke-width": 4 }));
      var ev = v.ev || {};
      // mark the objects this step hit: in the current or the target lane, reaching the
      // agent this step (a car moves 1 per step, a grandma 3)
      var marks = [["collisions", 1, 1, "✕", C.bad, "collision"], ["rescues", 2, 3, "★", C.good, "rescue"]];
      marks.forEach(function (m) {
        if (!ev[m[0]] || !(ev[m[0]][t] > 0)) return;
        var hit = f[m[1]].filter(function (o) { return o[1] <= m[2] && (o[0] === lane || o[0] === to); });
        if (!hit.length) hit = [[to, 0]];
        hit.forEach(function (o) {
          root.appendChild(svg("text", { x: x(o[0]) + w / 2, y: y(o[1]) + h / 2 + 8, "text-anchor": "middle",
            "font-size": 26, fill: m[4], stroke: "#fff", "stroke-width": 1.5, "font-weight": 700, "class": m[5] }, m[3]));
        });
      });
    }
    return root;
  }

  function picture(v, t) {
    if (v.picture && v.picture.kind === "findmilk") return findmilkPicture(v, t);
    if (v.picture && v.picture.kind === "driving") return drivingPicture(v, t);
    return el("pre", "", v.frames[Math.min(t, v.frames.length - 1)]);
  }

  function eventsText(v, t) {
    var out = [], ev = v.ev || {};
    var names = {
      crying_pacified: ["pacified a crying baby", "good"], sleeping_woken: ["woke a sleeping baby", "bad"],
      reached_milk: ["reached the milk", "good"], collisions: ["collision", "bad"], rescues: ["rescued a grandma", "good"],
      lane_changes: ["changed lane", ""]
    };
    for (var key in ev) {
      if (t < ev[key].length && ev[key][t] > 0) {
        var n = names[key] || [key, ""];
        out.push([n[0] + (ev[key][t] > 1 ? " ×" + ev[key][t] : ""), n[1]]);
      }
    }
    return out;
  }

  // ---------------------------------------------------------------- one variant
  function Variant(v, index) {
    this.v = v;
    this.step = 0;
    var sec = this.section = el("section", "variant");
    sec.id = "variant-" + index;
    sec.setAttribute("data-variant", v.name);
    sec.setAttribute("data-steps", String(v.T));
    if (v.note) sec.appendChild(el("p", "note", v.note));
    var self = this;
    // timeline: one tick per env step, height = Dempster's conflict K of its state
    var tl = el("div", "timeline");
    var panelKind = v.kind === "panel";
    var metricName = panelKind ? "conflict K" : "feedback for the action taken";
    tl.appendChild(el("h3", "", "Timeline: " + metricName + " per step, base/fine-tune disagreements, events (click to jump)"));
    var ticks = this.ticks = el("div", "ticks");
    var evrow = el("div", "evrow");
    this.tickNodes = [];
    this.disagreements = [];
    for (var t = 0; t < v.T; t++) {
      var tick = el("div", "tick");
      tick.setAttribute("data-step", String(t));
      var k = this.metric(t);
      var fill = el("div", "k");
      fill.style.height = (k === null ? 0 : Math.max(0.02, k) * 100) + "%";
      tick.appendChild(fill);
      var differs = v.b && v.b[t] !== v.a[t];
      if (differs) { tick.classList.add("disagree"); this.disagreements.push(t); }
      tick.title = "step " + t + ": " + ACTIONS[v.a[t]] + (v.b ? " (base " + ACTIONS[v.b[t]] + ")" : "") +
        (k === null ? "" : ", " + metricName + " " + fmt(k));
      ticks.appendChild(tick);
      this.tickNodes.push(tick);
      var evs = eventsText(v, t), good = false, bad = false;
      evs.forEach(function (e) { if (e[1] === "good") good = true; if (e[1] === "bad") bad = true; });
      evrow.appendChild(el("div", "ev" + (good && bad ? " both" : good ? " good" : bad ? " bad" : "")));
    }
    ticks.addEventListener("click", function (e) {
      var node = e.target.closest ? e.target.closest(".tick") : null;
      if (node) self.go(parseInt(node.getAttribute("data-step"), 10));
    });
    tl.appendChild(ticks);
    tl.appendChild(evrow);
    var legend = el("div", "legend");
    legend.appendChild(el("span", "swatch k")); legend.appendChild(document.createTextNode(metricName + " (0..1)"));
    legend.appendChild(el("span", "swatch dis")); legend.appendChild(document.createTextNode("fine-tuned action ≠ base action (" + this.disagreements.length + " steps)"));
    legend.appendChild(el("span", "swatch good")); legend.appendChild(document.createTextNode("good / bad event below"));
    legend.appendChild(el("span", "swatch cur")); legend.appendChild(document.createTextNode("current step"));
    tl.appendChild(legend);
    sec.appendChild(tl);
    var top = el("div", "top");
    var pic = el("div", "picture");
    this.pic = el("div", "pic");
    pic.appendChild(this.pic);
    this.caption = el("div", "caption");
    pic.appendChild(this.caption);
    top.appendChild(pic);
    var side = this.side = el("div", "side");
    top.appendChild(side);
    sec.appendChild(top);

    var nav = el("div", "card");
    var bar = el("div", "stepbar");
    var prev = el("button", "prev", "◀");
    prev.title = "previous step (ArrowLeft)";
    prev.addEventListener("click", function () { self.go(self.step - 1); });
    var next = el("button", "next", "▶");
    next.title = "next step (ArrowRight)";
    next.addEventListener("click", function () { self.go(self.step + 1); });
    this.label = el("span", "step-label");
    bar.appendChild(prev); bar.appendChild(this.label); bar.appendChild(next);
    bar.appendChild(el("span", "keys", "← → step · Home/End · PageUp/PageDown ±10 · [ ] previous/next disagreement"));
    nav.appendChild(bar);
    this.decision = el("div", "decision");
    nav.appendChild(this.decision);
    this.events = el("div", "events");
    nav.appendChild(this.events);
    side.appendChild(nav);
    this.detail = el("div", "detail");
    side.appendChild(this.detail);

  }

  Variant.prototype.state = function (t) { return this.v.s ? this.v.s[t] : null; };
  // the timeline's bar: Dempster's conflict K of a panel, else the feedback's belief in
  // the action taken (the fine-tune's reward)
  Variant.prototype.metric = function (t) {
    var st = this.v.st, u = this.state(t);
    if (this.v.kind !== "panel") return st && st.f && u !== null ? st.f[u][this.v.a[t]] : null;
    return this.conflict(t);
  };
  Variant.prototype.conflict = function (t) {
    var st = this.v.st, u = this.state(t);
    if (!st || !st.k || u === null || !st.k[u] || !st.k[u].length) return null;
    return st.k[u][0];
  };

  Variant.prototype.go = function (t) {
    var v = this.v;
    t = Math.max(0, Math.min(v.T - 1, t | 0));
    if (v.T === 0) t = 0;
    var old = this.tickNodes[this.step];
    if (old) old.classList.remove("current");
    this.step = t;
    this.section.setAttribute("data-step", String(t));
    var cur = this.tickNodes[t];
    if (cur) cur.classList.add("current");
    this.render();
    try { history.replaceState(null, "", "#" + encodeURIComponent(v.name) + ":" + t); } catch (e) { /* file: URLs */ }
  };

  Variant.prototype.render = function () {
    var v = this.v, t = this.step, u = this.state(t), st = v.st;
    clear(this.pic);
    this.pic.appendChild(picture(v, t));
    this.caption.textContent = "State before step " + t + (t < v.T ? " (the arrow is the fine-tuned action)" : "") + ". " + (v.picture_note || "");
    this.label.textContent = "step " + t + " / " + Math.max(0, v.T - 1);
    clear(this.decision);
    if (t < v.T) {
      var a = v.a[t];
      var mine = el("span", "taken");
      mine.appendChild(document.createTextNode("fine-tuned (" + v.mode + "): "));
      mine.appendChild(el("b", "action", ACTIONS[a]));
      mine.appendChild(document.createTextNode(" p=" + fmt(v.p[t][a])));
      this.decision.appendChild(mine);
      if (v.b) {
        var base = el("span", "base-action");
        base.appendChild(document.createTextNode("base (greedy): "));
        base.appendChild(el("b", "", ACTIONS[v.b[t]]));
        this.decision.appendChild(base);
      } else {
        this.decision.appendChild(el("span", "base-action", "base policy: not found"));
      }
      var flag = el("span", "flag-disagree", "differs from base");
      flag.hidden = !(v.b && v.b[t] !== a);
      this.decision.appendChild(flag);
      if (v.r) this.decision.appendChild(el("span", "reward", "r_env " + fmt(v.r[t], 2)));
    }
    clear(this.events);
    var evs = eventsText(v, t);
    if (!evs.length) this.events.textContent = "no event on this step";
    evs.forEach(function (e, i) {
      if (i) this.events.appendChild(document.createTextNode(" · "));
      this.events.appendChild(el("span", e[1], e[0]));
    }, this);

    clear(this.detail);
    // the policies
    var pol = el("div", "card");
    pol.appendChild(el("h3", "", "Policies: action probabilities"));
    var two = el("div", "agents");
    var p1 = el("div", "agent policy"); p1.appendChild(el("div", "agent-name", "fine-tuned")); p1.appendChild(bars(v.p[t], { cls: "policy", taken: v.a[t] }));
    two.appendChild(p1);
    if (v.bp) { var p2 = el("div", "agent base"); p2.appendChild(el("div", "agent-name", "base")); p2.appendChild(bars(v.bp[t], { cls: "base", taken: v.b[t] })); two.appendChild(p2); }
    pol.appendChild(two);
    this.detail.appendChild(pol);
    if (!st || u === null) {
      var none = el("div", "card");
      none.appendChild(el("h3", "", "Feedback"));
      none.appendChild(el("p", "", v.kind === "none" ? "This variant was not fine-tuned on feedback: no beliefs to show." : "No beliefs recorded."));
      this.detail.appendChild(none);
      return;
    }
    // fused belief and conflict
    var fused = el("div", "card fused");
    var k = st.k && st.k[u] && st.k[u].length ? st.k[u] : null;
    fused.appendChild(el("h3", "", (v.kind === "panel" ? "Fused belief (" + v.rule + ")" : "Feedback belief") +
      (k ? " · Dempster's conflict K = " + fmt(k[0]) : "")));
    fused.appendChild(bars(st.f[u], { cls: "fused", taken: v.a[t] }));
    if (k && k.length > 1) fused.appendChild(el("div", "conflicts", "K at each combination: " + k.map(function (x, i) { return "K" + (i + 1) + "=" + fmt(x); }).join("  ")));
    this.detail.appendChild(fused);
    // each agent
    var card = el("div", "card");
    card.appendChild(el("h3", "", v.kind === "panel" ? "Panel agents: belief, fusion weight, status, reasoning" : "Feedback source"));
    var grid = el("div", "agents");
    for (var c = 0; c < v.agents.length; c++) {
      var status = v.statuses[st.s[u][c]];
      var answered = ANSWERED[status] === 1;
      var box = el("div", "agent" + (answered ? "" : " abstained"));
      box.setAttribute("data-agent", v.agents[c]);
      box.setAttribute("data-status", status);
      var head = el("div", "agent-head");
      head.appendChild(el("span", "agent-name", v.agents[c]));
      head.appendChild(el("span", "status" + (answered ? "" : " failed"), answered ? status : status + " (abstains)"));
      box.appendChild(head);
      if (st.w) {
        var w = st.w[u][c];
        var wl = el("div", "weight", "fusion weight " + fmt(w));
        wl.setAttribute("data-weight", String(w));
        box.appendChild(wl);
        var wt = el("div", "wtrack"), wb = el("div", "wbar");
        wb.style.width = (Math.max(0, Math.min(1, w)) * 100) + "%";
        wt.appendChild(wb); box.appendChild(wt);
      }
      box.appendChild(bars(st.b[u][c], { taken: v.a[t] }));
      if (v.kind !== "panel") { grid.appendChild(box); continue; }
      var raw = st.x ? text(st.x[u][c]) : null;
      var why = st.why ? text(st.why[u][c]) : null;
      var det = el("details", "reasoning");
      det.appendChild(el("summary", "", raw ? "reasoning (raw reply)" : "reasoning: not kept"));
      det.appendChild(el("pre", "text raw", raw || (why ? "(" + why + ")" : (v.raw_note || "The store and the recording keep no reply text for this answer."))));
      box.appendChild(det);
      grid.appendChild(box);
    }
    card.appendChild(grid);
    this.detail.appendChild(card);
    var prompt = st.q ? text(st.q[u]) : null;
    var more = el("div", "card");
    if (prompt) {
      var pd = el("details", "prompt");
      pd.appendChild(el("summary", "", v.kind === "panel" ? "state prompt the agents were shown" : "state prompt (as an LLM panel would be shown it)"));
      pd.appendChild(el("pre", "text", prompt));
      more.appendChild(pd);
    }
    if (v.explain && v.kind === "panel") {
      var ex = el("div", "explain");
      ex.appendChild(document.createTextNode("Fusion's intermediate quantities (BJS, credibility, entropy): "));
      ex.appendChild(el("code", "cmd", v.explain.replace("{step}", String(t))));
      more.appendChild(ex);
    }
    if (more.firstChild) this.detail.appendChild(more);
  };

  // ---------------------------------------------------------------- the page
  var app = document.getElementById("app");
  clear(app);
  var header = el("header");
  header.appendChild(el("h1", "", DATA.title));
  header.appendChild(el("p", "meta", DATA.subtitle));
  app.appendChild(header);
  var tabs = el("nav", "tabs");
  tabs.id = "variant-tabs";
  tabs.setAttribute("role", "tablist");
  app.appendChild(tabs);
  var views = [], current = null;
  function select(i) {
    views.forEach(function (view, j) {
      view.section.hidden = j !== i;
      view.tab.setAttribute("aria-selected", j === i ? "true" : "false");
    });
    current = views[i];
    document.body.setAttribute("data-variant", current.v.name);
    current.go(current.step);
  }
  DATA.variants.forEach(function (v, i) {
    var view = new Variant(v, i);
    var tab = el("button", "", v.name);
    tab.setAttribute("role", "tab");
    tab.setAttribute("data-variant", v.name);
    tab.addEventListener("click", function () { select(i); });
    view.tab = tab;
    tabs.appendChild(tab);
    app.appendChild(view.section);
    views.push(view);
  });
  var footer = el("footer", "", DATA.footer);
  app.appendChild(footer);

  document.addEventListener("keydown", function (e) {
    if (!current || e.altKey || e.ctrlKey || e.metaKey) return;
    var s = current.step, target = null;
    if (e.key === "ArrowRight") target = s + 1;
    else if (e.key === "ArrowLeft") target = s - 1;
    else if (e.key === "Home") target = 0;
    else if (e.key === "End") target = current.v.T - 1;
    else if (e.key === "PageDown") target = s + 10;
    else if (e.key === "PageUp") target = s - 10;
    else if (e.key === "]") { target = current.disagreements.filter(function (x) { return x > s; })[0]; }
    else if (e.key === "[") { var before = current.disagreements.filter(function (x) { return x < s; }); target = before[before.length - 1]; }
    if (target === null || target === undefined) return;
    e.preventDefault();
    current.go(target);
  });

  // a link "#<variant>:<step>" opens that variant at that step; any other fragment
  // (malformed percent escapes, an unknown name, a huge step) is ignored, never an error
  function fromHash() {
    var hash;
    try {
      hash = decodeURIComponent(String(location.hash || "").slice(1, 2049));
    } catch (err) {
      return false;
    }
    if (!hash) return false;
    var cut = hash.lastIndexOf(":");
    var name = cut >= 0 ? hash.slice(0, cut) : hash;
    for (var i = 0; i < views.length; i++) {
      if (views[i].v.name === name) {
        views[i].step = Math.max(0, Math.min(views[i].v.T - 1, parseInt(hash.slice(cut + 1), 10) || 0));
        if (views[i] !== current) select(i); else current.go(views[i].step);
        return true;
      }
    }
    return false;
  }
  window.addEventListener("hashchange", fromHash);
  if (views.length && !fromHash()) select(0);
  document.body.setAttribute("data-ready", "1");
})();
