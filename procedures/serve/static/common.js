// Shared helpers of the pages: JSON fetch, units at the display edge, small SVG plots.
"use strict";
const UM = 1e6, ARCSEC = 180 * 3600 / Math.PI;  // m → µm, rad → ″

async function getJSON(url) {
  const response = await fetch(url, { credentials: "same-origin" });
  if (!response.ok) throw new Error(`${url}: ${response.status}`);
  return response.json();
}

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  for (const c of children) node.append(c);
  return node;
}

const SVGNS = "http://www.w3.org/2000/svg";
function svgEl(tag, attrs = {}) {
  const node = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  return node;
}

function when(seconds) { return seconds ? new Date(seconds * 1000).toLocaleString() : "—"; }
function clock(seconds) {
  if (seconds === null || seconds === undefined) return "--:--";
  const s = Math.round(seconds);
  return `${Math.floor(s / 3600)}:${String(Math.floor(s / 60) % 60).padStart(2, "0")}:${String(s % 60).padStart(2, "0")}`;
}
function fixed(value, digits, scale = 1) {
  return value === null || value === undefined ? "–" : (value * scale).toFixed(digits);
}
function stateBadge(state) { return el("span", { class: `state ${state}` }, state); }

// A scatter plot: points [[x, y], ...] in display units, symmetric axes about 0 when centred.
function scatter(points, { size = 160, label = "", highlightLast = true } = {}) {
  const svg = svgEl("svg", { viewBox: `0 0 ${size} ${size}`, class: "plot", role: "img", "aria-label": label });
  const extent = Math.max(1e-9, ...points.map(([x, y]) => Math.max(Math.abs(x), Math.abs(y)))) * 1.15;
  const map = (v) => size / 2 + (v / extent) * (size / 2 - 8);
  svg.append(svgEl("line", { x1: 0, y1: size / 2, x2: size, y2: size / 2, stroke: "#ddd" }));
  svg.append(svgEl("line", { x1: size / 2, y1: 0, x2: size / 2, y2: size, stroke: "#ddd" }));
  points.forEach(([x, y], i) => {
    const last = highlightLast && i === points.length - 1;
    svg.append(svgEl("circle", { cx: map(x), cy: size - map(y), r: last ? 4 : 2.5, class: "pt",
                                 fill: last ? "#b00020" : "#1f5fa8", "fill-opacity": 0.8 }));
  });
  const text = svgEl("text", { x: 4, y: size - 4, "font-size": 9, fill: "#666" });
  text.textContent = `±${extent.toPrecision(2)}`;
  svg.append(text);
  return svg;
}
