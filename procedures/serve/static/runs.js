// The runs list: filters go to /api/runs; the list refreshes whenever the store changes (/api/changes).
"use strict";
const controls = ["search", "state", "procedure"].map((id) => document.getElementById(id));

async function refresh() {
  const [q, state, procedure] = controls.map((c) => c.value);
  const data = await getJSON(`/api/runs?${new URLSearchParams({ q, state, procedure })}`);
  const body = document.querySelector("#runs tbody");
  body.replaceChildren(...data.runs.map((r) => el("tr", { "data-run": r.id },
    el("td", {}, el("a", { href: `/runs/${r.id}` }, r.id.slice(0, 12))),
    el("td", {}, stateBadge(r.state)),
    el("td", { class: "num" }, `${r.done ?? 0}/${r.total ?? 0}`),
    el("td", {}, r.title || r.name || r.procedure),
    el("td", {}, el("a", { href: `/robots?key=${encodeURIComponent(r.robot.key)}` }, r.station || "")),
    el("td", {}, when(r.created)),
    el("td", {}, el("a", { href: `/runs/${r.id}/report` }, "report")))));
  document.getElementById("matched").textContent = `(${data.matched})`;
}

controls.forEach((c) => c.addEventListener("input", refresh));
new EventSource("/api/changes").addEventListener("version", refresh);
refresh();
