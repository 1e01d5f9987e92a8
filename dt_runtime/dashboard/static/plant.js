// The plant page: /api/plant every 2 s into one table row per cell (dashboard/plant.py).
// Built with textContent only: names and reasons come from the bus.
"use strict";
const P = { rows: [], polls: 0 };
window.P = P;

function cellText(td, text, cls) {
  td.textContent = text;
  if (cls) td.className = cls;
  return td;
}

function render(snap) {
  const body = document.querySelector("#cells tbody");
  body.replaceChildren();
  for (const c of snap.cells) {
    const name = `${c.cell}/${c.robot}`;
    const tr = document.createElement("tr");
    tr.dataset.cell = name;
    tr.className = c.silent ? "silent" : "";
    const first = document.createElement("td");
    if (c.dashboard) {
      const a = document.createElement("a");
      a.href = c.dashboard;
      a.textContent = name;
      first.append(a);
      tr.classList.add("link");
      tr.addEventListener("click", (e) => { if (e.target.tagName !== "A") window.location.href = c.dashboard; });
    } else {
      first.textContent = name;
    }
    tr.append(first);
    const status = c.silent ? (c.age_s === null ? "silent (never heard)" : "silent") : (c.status || "?");
    tr.append(cellText(document.createElement("td"), status, "status " + (c.silent ? "bad" : c.status || "")));
    tr.append(cellText(document.createElement("td"), c.escalation || "", "escalation " + (c.escalation || "")));
    tr.append(cellText(document.createElement("td"), c.open_requests === undefined ? "" : String(c.open_requests),
                       "open"));
    tr.append(cellText(document.createElement("td"), c.age_s === null ? "never" : `${c.age_s.toFixed(1)} s ago`, "age"));
    tr.append(cellText(document.createElement("td"), c.dashboard ? "open" : "not listed", "muted"));
    body.append(tr);
  }
  const heard = snap.cells.filter((c) => !c.silent).length;
  const silent = snap.cells.filter((c) => c.silent && c.expected).map((c) => `${c.cell}/${c.robot}`);
  document.getElementById("summary").textContent =
    `${heard} cell(s) heard, ${snap.queries} quer${snap.queries === 1 ? "y" : "ies"} every ${snap.period_s} s` +
    (silent.length ? `; silent: ${silent.join(", ")}` : "");
  P.rows = snap.cells;
}

async function poll() {
  try {
    const r = await fetch("/api/plant", { cache: "no-store" });
    if (!r.ok) throw new Error(`${r.status}`);
    render(await r.json());
    P.polls += 1;
    document.getElementById("status").textContent = "";
  } catch (e) {
    document.getElementById("status").textContent = `the server does not answer (${e.message})`;
  }
  setTimeout(poll, 2000);
}
poll();
