"use strict";
// ppm-web's page: asks /api/state 20 times a second and draws every output.
// Plain script, no build step, nothing loaded from elsewhere. The numbers
// shown carry data-src / data-field attributes, which the browser test reads.

const SVG_NS = "http://www.w3.org/2000/svg";
const PERIOD_MS = 50;
const TIMEOUT_MS = 2000;
const STATE_NAMES = {
  flying: "FLYING", failsafe: "FAILSAFE", silent: "SILENT", not_running: "PPMD NOT RUNNING",
};
const TAKEOVER = {
  following: "radio transmits ppm's values",
  overridden: "INSTRUCTOR HAS TAKEN OVER",
  no_input: "no read-back signal",
  stale: "read-back: nothing from ppmd",
};
const COLORS = { command: "var(--cmd)", line: "var(--out)", readback: "var(--rb)" };
const views = new Map();

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  for (const c of children) e.append(c);
  return e;
}

function svg(tag, attrs) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  return e;
}

// Microseconds as shown: to a tenth, without a trailing ".0".
function us(v) {
  return v === undefined || v === null ? "\u2013" : String(Math.round(v * 10) / 10);
}

function ms(v) {
  if (v === undefined || v === null) return "\u2013";
  return v < 1000 ? v.toFixed(1) + " ms" : (v / 1000).toFixed(1) + " s";
}

function setText(e, text) {
  if (e.textContent !== text) e.textContent = text;
}

// The elements of one output, made once.
function build(o) {
  const root = el("section", { class: "output", "data-output": o.name });
  const r = { root, rows: [], hist: "" };
  r.state = el("span", { class: "badge", "data-field": "line-state" });
  r.degraded = el("span", { class: "badge small hidden", "data-state": "degraded", "data-field": "degraded" }, "DEGRADED RUN");
  r.takeover = el("span", { class: "badge small hidden", "data-field": "takeover" });
  r.meta = el("span", { class: "meta", "data-field": "meta" });
  r.error = el("div", { class: "err hidden", "data-field": "error" });
  root.append(el("div", { class: "head" }, el("h2", {}, o.name), r.state, r.degraded, r.takeover, r.meta), r.error);

  const hasRb = o.readback !== null && o.readback !== undefined;
  const left = el("div", {});
  const legend = el("span", { class: "note" },
    el("span", { class: "key cmd" }), "newest command",
    el("span", { class: "key out" }), "on the line");
  if (hasRb) legend.append(el("span", { class: "key rb" }), "radio transmits (read-back)");
  left.append(el("h3", {}, "Channels (\u00b5s) ", legend));
  r.sticks = buildSticks(o, left, hasRb);
  const table = el("table", { class: "chan" });
  const head = el("tr", {}, el("th", {}, ""), el("th", {}, ""), el("th", {}, "command"), el("th", {}, "line"));
  if (hasRb) head.append(el("th", {}, "radio"));
  table.append(head);
  o.channels.forEach((name, i) => {
    const bars = svg("svg", { class: "bars", viewBox: "0 0 1000 30", preserveAspectRatio: "none" });
    bars.append(svg("line", { x1: 500, x2: 500, y1: 0, y2: 30, stroke: "#c9d0d8", "stroke-width": 2 }));
    const rects = {};
    ["command", "line", "readback"].forEach((src, k) => {
      if (src === "readback" && !hasRb) return;
      rects[src] = svg("rect", { x: 0, y: 1 + k * 10, height: 8, width: 0, fill: COLORS[src] });
      bars.append(rects[src]);
    });
    const cells = {
      command: el("td", { class: "v", "data-src": "command" }),
      line: el("td", { class: "v", "data-src": "line" }),
    };
    const tr = el("tr", { "data-ch": String(i) }, el("td", { class: "n" }, name), el("td", { class: "bar" }, bars), cells.command, cells.line);
    if (hasRb) {
      cells.readback = el("td", { class: "v", "data-src": "readback" });
      tr.append(cells.readback);
    }
    table.append(tr);
    r.rows.push({ rects, cells });
  });
  left.append(table);

  const right = el("div", {});
  right.append(el("h3", {}, "Line, ppmd and udp-ingress"));
  const counters = el("table", { class: "counters" });
  r.fields = {};
  for (const [key, label] of [
    ["ppmd", "ppmd"], ["frames", "frames"], ["late", "late"], ["failsafe", "failsafe entries"],
    ["edge", "edge error (last 1 s)"], ["ingress", "udp-ingress"], ["datagrams", "commands"],
    ["rejected", "rejected"], ["mavlink", "MAVLink peers"], ["command", "newest command"],
    ["latency", "latency"], ["readback", "read-back"], ["telemetry", "flight controller"],
  ]) {
    const v = el("td", { class: "v", "data-field": key });
    const tr = el("tr", {}, el("td", {}, label), v);
    if ((key === "readback" && !hasRb) || key === "telemetry") tr.classList.add("hidden");
    counters.append(tr);
    r.fields[key] = v;
  }
  right.append(counters);
  r.histTitle = el("h3", {}, "Edge error");
  r.histSvg = svg("svg", { class: "hist", viewBox: "0 0 600 190", "data-field": "histogram" });
  right.append(r.histTitle, r.histSvg);
  root.append(el("div", { class: "grid" }, left, right));
  return r;
}

// Mode 2 sticks (left: rudder and throttle, right: aileron and elevator)
// when the output has those channels.
function buildSticks(o, parent, hasRb) {
  const at = (n) => o.channels.indexOf(n);
  const pairs = [["rud", "thr"], ["ail", "ele"]].map(([x, y]) => [at(x), at(y)]);
  if (pairs.some(([x, y]) => x < 0 || y < 0)) return null;
  const box = el("div", { class: "sticks" });
  const sticks = pairs.map(([x, y]) => {
    const s = svg("svg", { viewBox: "0 0 100 100" });
    s.append(svg("rect", { x: 1, y: 1, width: 98, height: 98, rx: 8, fill: "#f4f6f8", stroke: "#c9d0d8" }));
    s.append(svg("line", { x1: 50, x2: 50, y1: 4, y2: 96, stroke: "#d9dee4" }));
    s.append(svg("line", { y1: 50, y2: 50, x1: 4, x2: 96, stroke: "#d9dee4" }));
    const dots = {};
    for (const [src, r] of [["readback", 9], ["line", 7], ["command", 4]]) {
      if (src === "readback" && !hasRb) continue;
      dots[src] = svg("circle", { r, cx: 50, cy: 50, fill: src === "command" ? COLORS[src] : "none", stroke: COLORS[src], "stroke-width": 2.5, visibility: "hidden" });
      s.append(dots[src]);
    }
    box.append(el("figure", {}, s, el("figcaption", {}, o.channels[x] + " / " + o.channels[y])));
    return { x, y, dots };
  });
  parent.append(box);
  return sticks;
}

// Where value v of channel i sits between its limits, 0..1.
function frac(o, i, v) {
  const lo = o.min_us[i], hi = o.max_us[i];
  return Math.min(1, Math.max(0, (v - lo) / (hi - lo || 1)));
}

function update(r, o) {
  setText(r.state, STATE_NAMES[o.line_state] || o.line_state);
  r.state.dataset.state = o.line_state;
  const p = o.ppmd;
  r.degraded.classList.toggle("hidden", !(p && p.degraded));
  setText(r.meta, o.protocol.toUpperCase() + " on " + o.output);
  r.error.classList.toggle("hidden", !o.ipc_error);
  setText(r.error, o.ipc_error ? "shared memory: " + o.ipc_error : "");
  const rb = o.readback;
  if (rb) {
    r.takeover.classList.remove("hidden");
    r.takeover.dataset.state = rb.state;
    setText(r.takeover, TAKEOVER[rb.state] || rb.state);
  }
  const sources = {
    command: o.command ? o.command.ch_us : [],
    line: o.line ? o.line.ch_us : [],
    readback: rb ? rb.ch_us : [],
  };
  r.rows.forEach((row, i) => {
    for (const [src, cell] of Object.entries(row.cells)) {
      const v = sources[src][i];
      setText(cell, us(v));
      const rect = row.rects[src];
      if (rect) rect.setAttribute("width", v === undefined ? 0 : Math.round(1000 * frac(o, i, v)));
    }
  });
  if (r.sticks) {
    for (const s of r.sticks) {
      for (const [src, dot] of Object.entries(s.dots)) {
        const vx = sources[src][s.x], vy = sources[src][s.y];
        const shown = vx !== undefined && vy !== undefined;
        dot.setAttribute("visibility", shown ? "visible" : "hidden");
        if (shown) {
          dot.setAttribute("cx", (6 + 88 * frac(o, s.x, vx)).toFixed(1));
          dot.setAttribute("cy", (94 - 88 * frac(o, s.y, vy)).toFixed(1));
        }
      }
    }
  }
  const f = r.fields;
  if (p) {
    const sched = p.priority > 0 ? "SCHED_FIFO " + p.priority : "normal scheduler";
    setText(f.ppmd, "running, pid " + p.pid + ", " + p.timing + " timing, " + sched +
      (p.cpu !== null ? ", CPU " + p.cpu : "") + (p.preempt_rt ? ", PREEMPT_RT" : ""));
    const whole = p.frames - p.aborted_frames - p.glitched_frames;
    setText(f.frames, whole + " whole, " + p.aborted_frames + " aborted, " + p.glitched_frames + " glitched" +
      (p.timing === "follow" ? " (" + p.repeats + " repeats)" : ""));
    setText(f.late, p.late_frames + " late frames, " + p.overruns + " overruns");
    setText(f.failsafe, String(p.failsafe_entries));
    const e = p.edge_error_last_us;
    setText(f.edge, "p50 " + e.p50.toFixed(2) + ", p99 " + e.p99.toFixed(2) + ", p99.9 " + e.p999.toFixed(2) + ", max " + e.max.toFixed(1) + " \u00b5s");
  } else {
    setText(f.ppmd, "not running");
    for (const k of ["frames", "late", "failsafe", "edge"]) setText(f[k], "\u2013");
  }
  const ing = o.ingress;
  const st = ing.status;
  setText(f.ingress, ing.running ? "running, " + ing.address : "not running (" + ing.address + ")");
  f.ingress.title = ing.error || "";
  if (st) {
    const d = st.datagrams;
    setText(f.datagrams, d.received + " received, " + d.applied + " applied, " + d.superseded + " superseded, " + d.stale + " stale");
    const total = Object.values(d.rejected).reduce((a, b) => a + b, 0);
    const reasons = Object.entries(d.rejected).filter(([, n]) => n > 0).map(([k, n]) => k + " " + n);
    setText(f.rejected, total + (reasons.length ? " (" + reasons.join(", ") + ")" : ""));
    setText(f.mavlink, String(st.mavlink ? st.mavlink.peers : 0));
    const pl = st.publish_latency_us;
    let lat = pl && pl.count ? "receive \u2192 ppmd p50 " + pl.p50.toFixed(0) + ", p99 " + pl.p99.toFixed(0) + ", max " + pl.max.toFixed(0) + " \u00b5s" : "receive \u2192 ppmd: none yet";
    if (o.command && o.command.to_line_ms !== null) lat += "; receive \u2192 line \u2264 " + o.command.to_line_ms.toFixed(1) + " ms";
    setText(f.latency, lat);
  } else {
    for (const k of ["datagrams", "rejected", "mavlink", "latency"]) setText(f[k], "\u2013");
  }
  const c = o.command;
  setText(f.command, c ? ms(c.age_ms) + " ago" + (c.seq !== null ? ", seq " + c.seq : "") +
    (c.clamped ? ", " + c.clamped + " clamped" : "") + (c.other_model ? ", REFUSED: another channel model" : "") : "none yet");
  if (rb) {
    setText(f.readback, rb.state + ", " + rb.frames + " frames (" + rb.matched + " matched, " + rb.mismatched + " other)" +
      (rb.max_diff_us !== null ? ", max diff " + rb.max_diff_us.toFixed(1) + " \u00b5s" : ""));
    f.readback.title = "input: " + rb.input;
  }
  // A CRSF output's telemetry: what the flight controller sends back.
  const t = st ? st.telemetry : null;
  f.telemetry.parentElement.classList.toggle("hidden", !t);
  if (t) {
    const parts = [t.state];
    if (t.battery) parts.push(t.battery.voltage_v.toFixed(1) + " V, " + t.battery.current_a.toFixed(1) + " A, " + t.battery.remaining_pct + " %");
    if (t.flight_mode) parts.push(t.flight_mode.mode);
    if (t.attitude) {
      const deg = (rad) => (rad * 180 / Math.PI).toFixed(0) + "\u00b0";
      parts.push("roll " + deg(t.attitude.roll_rad) + " pitch " + deg(t.attitude.pitch_rad) + " yaw " + deg(t.attitude.yaw_rad));
    }
    if (t.gps) parts.push("GPS " + t.gps.satellites + " satellites, " + t.gps.altitude_m + " m");
    setText(f.telemetry, parts.join("; "));
    f.telemetry.title = "on " + t.port + ": " + t.frames + " frames, " + Object.values(t.bad).reduce((a, b) => a + b, 0) + " bad";
  }
  drawHistogram(r, o.histogram);
}

// The edge error of the last seconds as jitter --plot draws it: x the
// error (us), y the count per 1 us bucket on a log scale, marks at p50,
// p99, p99.9 and max.
function drawHistogram(r, h) {
  const key = h ? JSON.stringify(h) : "";
  if (key === r.hist) return;
  r.hist = key;
  const s = r.histSvg;
  while (s.firstChild) s.removeChild(s.firstChild);
  if (!h || h.count === 0) {
    setText(r.histTitle, "Edge error");
    const t = svg("text", { x: 300, y: 95, "text-anchor": "middle", fill: "#6b7480", "font-size": 13 });
    t.textContent = "no edges yet";
    s.append(t);
    return;
  }
  setText(r.histTitle, "Edge error, last " + h.window_s.toFixed(1) + " s (" + h.count + " edges)");
  // Errors of 1 ms or more (the overflow) get a slot of their own at the
  // right, so that they do not squeeze the rest.
  const L = 46, R = h.overflow ? 550 : 590, T = 22, B = 160;
  const top = h.buckets.length ? h.buckets[h.buckets.length - 1][0] + 1 : 1;
  const xmax = niceCeil(Math.max(top, 10));
  const cmax = Math.max(1, ...h.buckets.map((b) => b[1]), h.overflow);
  const ydec = Math.max(1, Math.ceil(Math.log10(cmax + 1)));
  const x = (v) => (v >= 1000 ? 575 : L + (R - L) * v / xmax);
  const y = (n) => B - (B - T) * Math.log10(n) / ydec;
  s.append(svg("line", { x1: L, x2: R, y1: B, y2: B, stroke: "#6b7480" }));
  s.append(svg("line", { x1: L, x2: L, y1: T, y2: B, stroke: "#6b7480" }));
  for (let d = 0; d <= ydec; d++) {
    s.append(svg("line", { x1: L - 3, x2: R, y1: y(10 ** d), y2: y(10 ** d), stroke: "#e6e9ed" }));
    const t = svg("text", { x: L - 5, y: y(10 ** d) + 4, "text-anchor": "end", "font-size": 11, fill: "#6b7480" });
    t.textContent = d === 0 ? "1" : "1e" + d;
    s.append(t);
  }
  for (let k = 0; k <= 5; k++) {
    const v = xmax * k / 5;
    const t = svg("text", { x: x(v), y: B + 15, "text-anchor": "middle", "font-size": 11, fill: "#6b7480" });
    t.textContent = String(Math.round(v));
    s.append(t);
  }
  const xl = svg("text", { x: (L + R) / 2, y: B + 29, "text-anchor": "middle", "font-size": 11, fill: "#6b7480" });
  xl.textContent = "edge error (\u00b5s), count per 1 \u00b5s on a log scale";
  s.append(xl);
  const w = Math.max(1, (R - L) / xmax);
  for (const [b, n] of h.buckets) {
    s.append(svg("rect", { x: x(b), y: y(n), width: w, height: Math.max(1, B - y(n)), fill: "#466eb4" }));
  }
  if (h.overflow) {
    s.append(svg("rect", { x: 565, y: y(h.overflow), width: 20, height: Math.max(1, B - y(h.overflow)), fill: "#c62828" }));
    const t = svg("text", { x: 575, y: T - 6, "text-anchor": "middle", "font-size": 11, fill: "#c62828" });
    t.textContent = "\u2265 1 ms";
    s.append(t);
  }
  const palette = ["#008c46", "#e67800", "#c80000", "#282828"];
  h.marks.forEach(([label, v], i) => {
    const xv = x(v);
    s.append(svg("line", { x1: xv, x2: xv, y1: T, y2: B, stroke: palette[i], "stroke-dasharray": "4 3" }));
    const right = xv > 480;
    const t = svg("text", { x: right ? xv - 3 : xv + 3, y: T + 10 + i * 12, "font-size": 11, fill: palette[i], "text-anchor": right ? "end" : "start" });
    t.textContent = label + (v >= 1000 ? " \u2265 1 ms" : " \u2264 " + v + " \u00b5s");
    s.append(t);
  });
}

function niceCeil(v) {
  const p = 10 ** Math.floor(Math.log10(v));
  for (const m of [1, 2, 5, 10]) if (m * p >= v) return m * p;
  return 10 * p;
}

function render(state) {
  const main = document.getElementById("outputs");
  const seen = new Set();
  for (const o of state.outputs) {
    seen.add(o.name);
    let r = views.get(o.name);
    if (!r) {
      r = build(o);
      views.set(o.name, r);
      main.append(r.root);
    }
    update(r, o);
  }
  for (const [name, r] of views) {
    if (!seen.has(name)) {
      r.root.remove();
      views.delete(name);
    }
  }
}

const conn = document.getElementById("conn");

async function poll() {
  const ctl = new AbortController();
  const timer = setTimeout(() => ctl.abort(), TIMEOUT_MS);
  try {
    const res = await fetch("/api/state", { cache: "no-store", signal: ctl.signal });
    if (!res.ok) throw new Error("HTTP " + res.status);
    render(await res.json());
    conn.dataset.state = "ok";
    setText(conn, "live");
  } catch (e) {
    // Said on the page, not in the console: ppm-web may be restarting.
    conn.dataset.state = "lost";
    setText(conn, "no answer from ppm-web (" + (e && e.name === "AbortError" ? "timeout" : "stopped?") + "), retrying");
  } finally {
    clearTimeout(timer);
    setTimeout(poll, PERIOD_MS);
  }
}

poll();
