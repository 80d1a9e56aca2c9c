// The live view: polls /api/state (SI units) and draws it. Nothing is loaded from
// anywhere but this server.
(function () {
  "use strict";

  // the report's colours (tissuecli/report/figures.py)
  const MEASURED = "#1f5fa8", OPENING = "#c0182b", CLOSURE = "#444444";
  const MIN_INTERVAL_MS = 50;  // at most 20 updates a second
  const $ = (id) => document.getElementById(id);

  // what the page last showed, for scripts and tests
  const view = (window.liveView = {
    updates: 0, updatesPerS: null, latencyMs: null, latencyMaxMs: null, state: null, errors: 0,
  });
  const recent = [];  // [time shown, latency] of the last updates

  function size(el, height) {
    return { width: Math.max(300, el.clientWidth), height: height };
  }

  function traceChart(el, label, colour, height) {
    return new uPlot({
      ...size(el, height),
      legend: { show: false },
      cursor: { show: false },
      scales: { x: { time: false } },
      axes: [
        { label: "time before the newest sample (s)", labelSize: 18 },
        { label: label, labelSize: 18, size: 56 },
      ],
      series: [{}, { stroke: colour, width: 1.2, points: { show: false } }],
    }, [[], []], el);
  }

  const force = traceChart($("force-chart"), "force F (N)", MEASURED, 210);
  const closure = traceChart($("closure-chart"), "closure x (mm)", CLOSURE, 180);

  // the loop is drawn in a draw hook on uPlot's axes: its points are not ordered in x
  let loopPoints = null;
  function drawLoop(u) {
    if (!loopPoints || loopPoints.x.length < 2) return;
    const ctx = u.ctx, box = u.bbox, p = loopPoints;
    ctx.save();
    ctx.beginPath();
    ctx.rect(box.left, box.top, box.width, box.height);
    ctx.clip();
    ctx.lineWidth = 1.3 * devicePixelRatio;
    ctx.lineJoin = "round";
    let current = null;
    for (let i = 1; i < p.x.length; i++) {
      const colour = p.closing[i] ? MEASURED : OPENING;
      if (colour !== current) {
        if (current) ctx.stroke();
        ctx.strokeStyle = current = colour;
        ctx.beginPath();
        ctx.moveTo(u.valToPos(p.x[i - 1], "x", true), u.valToPos(p.f[i - 1], "y", true));
      }
      ctx.lineTo(u.valToPos(p.x[i], "x", true), u.valToPos(p.f[i], "y", true));
    }
    ctx.stroke();
    ctx.restore();
  }
  const loop = new uPlot({
    ...size($("loop-chart"), 300),
    legend: { show: false },
    cursor: { show: false },
    scales: { x: { time: false } },
    axes: [
      { label: "jaw closure x (mm)", labelSize: 18 },
      { label: "grasp force F (N)", labelSize: 18, size: 56 },
    ],
    series: [{}, { stroke: "transparent", points: { show: false } }],
    hooks: { draw: [drawLoop] },
  }, [[], []], $("loop-chart"));

  function resize() {
    force.setSize(size($("force-chart"), 210));
    closure.setSize(size($("closure-chart"), 180));
    loop.setSize(size($("loop-chart"), 300));
  }
  window.addEventListener("resize", resize);

  function setValue(id, value, text) {
    const el = $(id);
    el.dataset.value = value;
    el.textContent = text;
  }

  function fmt(v) {
    if (v === null || v === undefined || !isFinite(v)) return "-";
    const a = Math.abs(v);
    return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(3) : v.toPrecision(4);
  }

  function renderStatus(s, st) {
    setValue("elapsed", s.elapsed_s, s.elapsed_s.toFixed(1) + " s");
    setValue("samples", s.samples, s.samples.toLocaleString("en"));
    setValue("rate", s.rate_hz, s.rate_hz.toFixed(1) + " Hz");
    setValue("lost", s.lost_frames, String(s.lost_frames));
    setValue("bad", s.bad_frames, String(s.bad_frames));
    setValue("file", s.file_bytes, (s.file_bytes / 1e6).toFixed(2) + " MB");
    $("session").textContent = st.session;
  }

  function renderTraces(tr) {
    const t = tr.time_s, n = t.length, newest = n ? t[n - 1] : 0;
    const rel = t.map((v) => v - newest);
    force.setData([rel, tr.force_n]);
    closure.setData([rel, tr.position_m.map((v) => v * 1e3)]);
    $("window").textContent = String(tr.window_s);
  }

  function renderLoop(lp) {
    const x = lp.position_m.map((v) => v * 1e3), f = lp.force_n;
    loopPoints = { x: x, f: f, closing: lp.closing };
    if (!x.length) { loop.setData([[], []]); return; }
    // two invisible points span the ranges, so that uPlot scales the axes
    const xs = [Math.min(...x), Math.max(...x)], fs = [Math.min(...f), Math.max(...f)];
    if (xs[0] === xs[1]) xs[1] += 1e-3;
    loop.setData([xs, fs]);
  }

  function row(cells, cls) {
    const tr = document.createElement("tr");
    if (cls) tr.className = cls;
    for (const c of cells) {
      const td = document.createElement("td");
      if (c instanceof Node) td.appendChild(c); else td.textContent = c;
      tr.appendChild(td);
    }
    return tr;
  }

  function renderEstimate(e) {
    const params = $("parameters"), probs = $("probabilities");
    $("identifying").hidden = !!e;
    params.hidden = probs.hidden = !e;
    $("law").textContent = e ? e.law + (e.confident ? "" : " (not yet confident)") : "";
    if (!e) return;
    const body = params.tBodies[0];
    body.replaceChildren(...e.names.map((name, i) => {
      const r = row([name, fmt(e.mean[i]),
        "[" + fmt(e.ci95[i][0]) + ", " + fmt(e.ci95[i][1]) + "]", e.units[i]]);
      r.dataset.mean = e.mean[i];
      return r;
    }));
    const ranked = Object.entries(e.probabilities).sort((a, b) => b[1] - a[1]);
    probs.tBodies[0].replaceChildren(...ranked.map(([law, p]) => {
      const bar = document.createElement("span");
      bar.className = "bar";
      bar.style.width = Math.round(120 * p) + "px";
      const r = row([law, (100 * p).toFixed(1) + " %", bar], law === e.law ? "chosen" : "");
      r.dataset.probability = p;
      return r;
    }));
  }

  function ended(text) {
    const line = $("state-line");
    line.textContent = text;
    line.className = "ended";
  }

  function painted() {
    return new Promise((resolve) => requestAnimationFrame(() => resolve()));
  }

  async function poll() {
    const sent = performance.now();
    let st;
    try {
      const response = await fetch("api/state", { cache: "no-store" });
      st = await response.json();
    } catch (err) {
      view.errors += 1;
      ended(view.state ? "recording ended (the recorder has stopped serving)" : "no recorder here");
      return;
    }
    renderStatus(st.status, st);
    renderTraces(st.traces);
    renderLoop(st.loop);
    renderEstimate(st.estimate);
    await painted();
    const shown = performance.now();
    // upper bound: the sample's age when the server answered plus the whole round trip
    const latency = st.sample_age_s === null ? null : st.sample_age_s * 1e3 + (shown - sent);
    view.state = st;
    view.updates += 1;
    recent.push([shown, latency]);
    while (recent.length && shown - recent[0][0] > 2000) recent.shift();
    if (recent.length > 1) {
      view.updatesPerS = (recent.length - 1) / ((shown - recent[0][0]) / 1e3);
      const lat = recent.map((r) => r[1]).filter((v) => v !== null);
      view.latencyMs = latency;
      view.latencyMaxMs = lat.length ? Math.max(...lat) : null;
      setValue("updates", view.updatesPerS, view.updatesPerS.toFixed(1) + " /s");
      if (latency !== null) {
        setValue("latency", latency, latency.toFixed(0) + " ms (max " + view.latencyMaxMs.toFixed(0) + ")");
      }
    }
    if (!st.running) { ended("recording ended"); return; }
    const line = $("state-line");
    line.textContent = "recording";
    line.className = "";
    setTimeout(poll, Math.max(0, MIN_INTERVAL_MS - (performance.now() - sent)));
  }

  poll();
})();
