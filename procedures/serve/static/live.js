// The live page of one run (/runs/RUN) or of the current run (/live): everything arrives as
// server-sent events from /api/runs/RUN/stream; nothing reloads the page.
"use strict";
const requested = location.pathname.startsWith("/runs/") ? location.pathname.split("/")[2] : "current";
let points = [];
const $ = (id) => document.getElementById(id);

function reset(runId) {
  points = [];
  $("scatter").replaceChildren();
  $("events").replaceChildren();
  $("frames").replaceChildren();
  $("results-section").hidden = true;
  $("posestream-section").hidden = true;
  $("posestream").replaceChildren();
  $("report").href = `/runs/${runId}/report`;
}

function showRun(run) {
  $("title").textContent = `${run.title || run.name || run.procedure} · ${run.id.slice(0, 12)} · ${run.station || ""}`;
  $("state").replaceChildren(stateBadge(run.state));
  $("done").textContent = run.done ?? 0;
  $("total").textContent = run.total ?? 0;
  $("bar").style.width = `${run.total ? (100 * run.done) / run.total : 0}%`;
  $("phase").textContent = [run.phase, run.cycle !== null && run.cycle !== undefined ? `cycle ${run.cycle + 1}` : "",
                            run.label].filter(Boolean).join(" · ");
  $("eta").textContent = run.state === "RUNNING" ? clock(run.eta_s) : "--:--";
  $("failed").textContent = run.failed ?? 0;
  $("reason").textContent = run.reason || "";
}

function showPoints(fresh) {
  points.push(...fresh);
  const last = points[points.length - 1];
  if (last) {
    $("last").textContent = last.ok && last.pose
      ? `${last.key}: x ${fixed(last.pose[0], 4, 1e3)} y ${fixed(last.pose[1], 4, 1e3)} z ${fixed(last.pose[2], 4, 1e3)} mm,` +
        ` residual ${fixed(last.residual_rms, 2, UM)} µm`
      : `${last.key}: FAILED ${last.error || ""}`;
  }
  // One small plot per point label (ISO P1…P5); a calibration with many labels gets one plot of all poses.
  // The ISO cycles only, once there are any (the transform pass visits the same points first).
  const measured = points.filter((p) => p.ok && p.pose);
  const good = measured.some((p) => p.phase === "iso") ? measured.filter((p) => p.phase === "iso") : measured;
  const labels = [...new Set(good.map((p) => p.label))];
  const groups = labels.length <= 12 ? labels.map((l) => [l, good.filter((p) => p.label === l)]) : [["all poses", good]];
  $("scatter").replaceChildren(...groups.map(([label, mine]) => {
    const mean = [0, 1].map((k) => mine.reduce((s, p) => s + p.pose[k], 0) / mine.length);
    const xy = mine.map((p) => [(p.pose[0] - mean[0]) * UM, (p.pose[1] - mean[1]) * UM]);
    return el("figure", { "data-label": label }, scatter(xy, { label }), el("figcaption", {}, `${label} · n = ${mine.length}`));
  }));
}

function showEvents(events) {
  for (const e of events) {
    $("events").prepend(el("li", {}, `${new Date(e.time * 1000).toLocaleTimeString()} ${e.kind} ${e.message || ""}`));
  }
}

function showFrames(frames) {
  $("frames-step").textContent = `(${frames.key}, ${frames.source})`;
  const [w, h] = frames.size;
  $("frames").replaceChildren(...Object.entries(frames.screens).map(([screen, f]) => {
    const svg = svgEl("svg", { viewBox: `0 0 ${w} ${h}`, "data-screen": screen });
    svg.append(svgEl("image", { href: f.url, x: 0, y: 0, width: w, height: h }));
    if (f.lines) {
      for (const part of ["horizontal", "vertical"]) {
        const [[x1, y1], [x2, y2]] = f.lines[part];
        svg.append(svgEl("line", { x1, y1, x2, y2, stroke: "#00e0ff", "stroke-width": w / 300, class: "stripe" }));
      }
      const [cx, cy] = f.lines.center;
      svg.append(svgEl("circle", { cx, cy, r: w / 40, fill: "none", stroke: "#ff3050", "stroke-width": w / 250, class: "cross" }));
    }
    const caption = f.cross ? `screen ${screen}: (${fixed(f.cross.center_px[0], 2)}, ${fixed(f.cross.center_px[1], 2)}) px`
                            : `screen ${screen}: no cross`;
    return el("figure", {}, svg, el("figcaption", {}, caption));
  }));
}

// A figure with its expanded uncertainty U (k = 2) when the results carry one.
const withU = (s, key, digits, scale) => fixed(s[key], digits, scale) +
  (s[`${key}_u`] != null ? ` ± ${fixed(s[`${key}_u`], digits, scale)}` : "");

function showResults(data) {
  const rows = Object.entries(data.iso_points || {});
  if (!rows.length) return;
  $("results-section").hidden = false;
  const head = el("tr", {}, ...["point", "n", "RP_l (µm)", "95 % CI", "RP_a (″)", "RP_b (″)", "RP_c (″)", "AP_P (µm)"]
    .map((t) => el("th", { class: "num" }, t)));
  $("results").replaceChildren(head, ...rows.map(([label, s]) => el("tr", {},
    el("td", {}, label), el("td", { class: "num" }, s.n ?? "–"), el("td", { class: "num" }, withU(s, "rp_l", 2, UM)),
    el("td", { class: "num" }, s.rp_l_ci ? `${fixed(s.rp_l_ci[0], 1, UM)}–${fixed(s.rp_l_ci[1], 1, UM)}` : "–"),
    el("td", { class: "num" }, withU(s, "rp_a", 2, ARCSEC)), el("td", { class: "num" }, withU(s, "rp_b", 2, ARCSEC)),
    el("td", { class: "num" }, withU(s, "rp_c", 2, ARCSEC)), el("td", { class: "num" }, withU(s, "ap_p", 1, UM)))));
}

// A move measured in motion (iso9283_stabilisation, iso9283_path): how far the tool was from where it came
// to rest, over the streamed seconds; the robot's done signal at 0.
function showPoseStream(d) {
  $("posestream-section").hidden = false;
  $("posestream-key").textContent = `(${d.key || d.step}, ${d.poses} poses at ${d.rate_hz} Hz, ${d.dropped} dropped)`;
  const w = 320, h = 160, pad = 30;
  const xs = d.t.map((t) => t * 1e3), ys = d.distance.map((v) => v * UM);
  const [x0, x1] = [Math.min(...xs), Math.max(...xs)], y1 = Math.max(...ys, 1e-9);
  const px = (x) => pad + ((x - x0) / (x1 - x0 || 1)) * (w - pad - 5), py = (y) => h - pad + 5 - (y / y1) * (h - pad);
  const svg = svgEl("svg", { viewBox: `0 0 ${w} ${h}`, class: "posestream", "data-step": d.step });
  svg.append(svgEl("polyline", { points: xs.map((x, i) => `${px(x).toFixed(1)},${py(ys[i]).toFixed(1)}`).join(" "),
                                 fill: "none", stroke: "#1f77b4", "stroke-width": 1, class: "distance" }));
  if (x0 <= 0 && x1 >= 0) {
    svg.append(svgEl("line", { x1: px(0), x2: px(0), y1: py(0), y2: py(y1), stroke: "#d62728", class: "done" }));
  }
  const label = (x, y, text) => { const t = svgEl("text", { x, y, "font-size": 9 }); t.textContent = text; return t; };
  svg.append(label(2, 10, `${fixed(y1, 1)} µm`), label(pad, h - 4, `${fixed(x0, 0)} ms`),
             label(w - 40, h - 4, `${fixed(x1, 0)} ms`));
  $("posestream").replaceChildren(svg);
}

const source = new EventSource(`/api/runs/${requested}/stream`);
const on = (name, handler) => source.addEventListener(name, (e) => handler(JSON.parse(e.data)));
on("switch", (d) => reset(d.run_id));
on("run", showRun);
on("points", showPoints);
on("events", showEvents);
on("frames", showFrames);
on("results", showResults);
on("posestream", showPoseStream);
on("waiting", (d) => { $("title").textContent = d.message; });
on("failure", (d) => { $("title").textContent = d.message; source.close(); });
source.onopen = () => { $("connection").textContent = "live"; };
source.onerror = () => { $("connection").textContent = "reconnecting…"; };
