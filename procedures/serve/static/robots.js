// Robots and each robot's RP history (finished ISO 9283 runs), refreshed when the store changes.
"use strict";
const COLOURS = ["#1f5fa8", "#b00020", "#2a7a2a", "#a86400", "#6a3d9a", "#00838f"];

function chart(history) {
  const labels = [...new Set(history.flatMap((h) => Object.keys(h.points)))];
  const width = 640, height = 220, pad = 36;
  const values = history.flatMap((h) => Object.values(h.points).flatMap((p) => p.rp_l_ci || [p.rp_l]))
    .filter((v) => v !== null && v !== undefined).map((v) => v * UM);
  const top = Math.max(1, ...values) * 1.1;
  const svg = svgEl("svg", { viewBox: `0 0 ${width} ${height}`, class: "plot", role: "img", "aria-label": "RP history" });
  const x = (i) => pad + (history.length > 1 ? (i * (width - 2 * pad)) / (history.length - 1) : (width - 2 * pad) / 2);
  const y = (v) => height - pad - (v / top) * (height - 2 * pad);
  for (const tick of [0, top / 2, top]) {
    svg.append(svgEl("line", { x1: pad, x2: width - pad, y1: y(tick), y2: y(tick), stroke: "#eee" }));
    const t = svgEl("text", { x: 2, y: y(tick) + 3, "font-size": 10, fill: "#666" });
    t.textContent = tick.toFixed(0);
    svg.append(t);
  }
  labels.forEach((label, k) => {
    const colour = COLOURS[k % COLOURS.length];
    history.forEach((h, i) => {
      const p = h.points[label];
      if (!p || p.rp_l === undefined || p.rp_l === null) return;
      const cx = x(i) + (k - labels.length / 2) * 4;
      if (p.rp_l_ci) svg.append(svgEl("line", { x1: cx, x2: cx, y1: y(p.rp_l_ci[0] * UM), y2: y(p.rp_l_ci[1] * UM), stroke: colour }));
      svg.append(svgEl("circle", { cx, cy: y(p.rp_l * UM), r: 3, fill: colour, class: "rp" }));
    });
    const legend = svgEl("text", { x: pad + k * 50, y: 12, "font-size": 11, fill: colour });
    legend.textContent = label;
    svg.append(legend);
  });
  return svg;
}

async function showHistory(key) {
  const data = await getJSON(`/api/robots/history?key=${encodeURIComponent(key)}`);
  document.getElementById("history-section").hidden = false;
  document.getElementById("robot").textContent = key.replace(/^(serial|station):/, "");
  document.getElementById("chart").replaceChildren(chart(data.history));
  const labels = [...new Set(data.history.flatMap((h) => Object.keys(h.points)))];
  document.getElementById("history").replaceChildren(
    el("tr", {}, el("th", {}, "run"), el("th", {}, "finished"), ...labels.map((l) => el("th", { class: "num" }, `${l} RP_l (µm)`))),
    ...data.history.map((h) => el("tr", {}, el("td", {}, el("a", { href: `/runs/${h.run.id}` }, h.run.id.slice(0, 12))),
      el("td", {}, when(h.run.finished)),
      ...labels.map((l) => el("td", { class: "num" }, h.points[l] ? fixed(h.points[l].rp_l, 2, UM) : "–")))));
}

async function refresh() {
  const data = await getJSON("/api/robots");
  document.querySelector("#robots tbody").replaceChildren(...data.robots.map((r) => el("tr", {},
    el("td", {}, el("a", { href: `/robots?key=${encodeURIComponent(r.key)}` }, r.label)),
    el("td", {}, r.source === "identity" ? "serial number" : "station name"),
    el("td", { class: "num" }, r.runs), el("td", { class: "num" }, r.iso_runs), el("td", {}, when(r.last)))));
  const key = new URLSearchParams(location.search).get("key") || (data.robots[0] && data.robots[0].key);
  if (key) await showHistory(key);
}

new EventSource("/api/changes").addEventListener("version", refresh);
