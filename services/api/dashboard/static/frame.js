/* Spaces whose up detection could not decide: the two candidates side by side, each with a side view of
   the scan under that up (a server-made PNG), and one click to pick; spaces whose units could not be
   decided (cm or inches): each candidate with the storey and size it gives the scan, one click to pick. Loaded before app.js; uses its
   helpers (h, api, fmtNum, token, API) only when called. */
"use strict";

async function authedImageUrl(path, retries = 6) {
  // <img> cannot send the Authorization header: fetch the picture and show it from a blob URL. A tenant's side
  // views are drawn a few at a time: a 429 is asked again after the Retry-After it names.
  for (let attempt = 0; ; attempt++) {
    const r = await fetch(API + path, { headers: { Authorization: `Bearer ${token()}` } });
    if (r.status === 429 && attempt < retries) {
      const seconds = Number(r.headers.get("Retry-After")) || 1;
      await new Promise((resume) => setTimeout(resume, seconds * 1000));
      continue;
    }
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    return URL.createObjectURL(await r.blob());
  }
}

function upCandidateFigure(space, cand, index, status, onPicked) {
  const img = h("img", { class: "up-preview", width: 240, height: 150,
                         alt: `${space.name} seen from the side with candidate ${index + 1} as up` });
  authedImageUrl(`/spaces/${space.id}/up-candidates/${index}.png`)
    .then((url) => { img.src = url; })
    .catch(() => { img.alt = "side view unavailable"; });
  const pick = h("button", { type: "button", class: "pick-up", dataset: { space: String(space.id), index: String(index) },
    onclick: async () => {
      pick.disabled = true;
      status.className = "muted";
      status.textContent = "Saving…";
      try {
        const saved = await api(`/spaces/${space.id}/up`, { method: "PUT", body: { up: cand.up } });
        status.textContent = `Up of "${saved.name}" set to [${saved.up_choice.up.map((x) => fmtNum(x, 3)).join(", ")}].`;
        onPicked(saved);
      } catch (ex) { status.className = "error"; status.textContent = ex.message; pick.disabled = false; }
    } }, "This way up");
  return h("figure", { class: "up-candidate" }, img,
    h("figcaption", {},
      h("strong", {}, ["Detection's best", "Runner-up", "Next"][index]),
      h("div", {}, `up [${cand.up.map((x) => fmtNum(x, 3)).join(", ")}]`),
      h("div", {}, `floor ${fmtNum(cand.floor_area_m2, 2)} m², storey ${fmtNum(cand.storey_height_m, 2)} m`),
      h("div", { class: "muted evidence", title: "evidence terms (log-odds): 0 is best, negative speaks against" },
        `score ${fmtNum(cand.score, 2)}: ` + Object.entries(cand.evidence || {})
          .map(([k, v]) => `${k.replace(/_/g, " ")} ${fmtNum(v, 2)}`).join(", "))),
    pick);
}

function unitChoiceButton(space, cand, status, onPicked) {
  const pick = h("button", { type: "button", class: "pick-units", dataset: { space: String(space.id), unit: cand.unit },
    onclick: async () => {
      pick.disabled = true;
      status.className = "muted";
      status.textContent = "Saving…";
      try {
        const saved = await api(`/spaces/${space.id}/up`, { method: "PUT", body: { unit_scale: cand.unit_scale } });
        status.textContent = `Units of "${saved.name}" set to ${fmtNum(saved.unit_scale, 4)} m per unit.`;
        onPicked(saved);
      } catch (ex) { status.className = "error"; status.textContent = ex.message; pick.disabled = false; }
    } }, `In ${cand.unit}`);
  return h("figure", { class: "unit-candidate" },
    h("figcaption", {},
      h("strong", {}, `${cand.unit} (×${cand.unit_scale})`),
      h("div", {}, `storey ${fmtNum(cand.storey_height_m, 2)} m, ${cand.extent_m.map((x) => fmtNum(x, 2)).join(" × ")} m`),
      h("div", { class: "muted evidence", title: "evidence terms (log-odds): 0 is neutral, negative speaks against" },
        `score ${fmtNum(cand.score, 2)}: ` + Object.entries(cand.evidence || {})
          .map(([k, v]) => `${k} ${fmtNum(v, 2)}`).join(", "))),
    pick);
}

// A card listing every space that needs its up (or, with its up decided, its units) picked; null when none does.
function needsFramePanel(spaces, onPicked) {
  const upPending = (s) => s.frame && s.frame.up && s.frame.up.ambiguous && (s.frame.up.candidates || []).length >= 2;
  const unitsPending = (s) => !upPending(s) && s.frame && s.frame.units && s.frame.units.ambiguous &&
    (s.frame.units.candidates || []).length >= 2;
  const pending = spaces.filter((s) => s.needs_frame && (upPending(s) || unitsPending(s)));
  if (!pending.length) return null;
  return h("div", { class: "card", id: "needs-frame" },
    h("h2", {}, "Which way is up?"),
    h("p", { class: "muted" }, "Detection could not tell these candidates apart, so jobs over these spaces are held. " +
      "Each picture shows the scan from the side with that candidate pointing up: pick the one standing on its floor. " +
      "Units: pick the one that gives the room its real size."),
    ...pending.map((s) => {
      const status = h("p", { class: "muted", role: "status" });
      if (unitsPending(s)) {
        return h("section", { class: "needs-frame-space", dataset: { space: String(s.id) } },
          h("h3", {}, `${s.name} (#${s.id}): which units?`),
          h("div", { class: "unit-candidates" }, ...s.frame.units.candidates.map((c) => unitChoiceButton(s, c, status, onPicked))),
          status);
      }
      const up = s.frame.up;
      return h("section", { class: "needs-frame-space", dataset: { space: String(s.id) } },
        h("h3", {}, `${s.name} (#${s.id}): ${fmtNum(100 * (up.probability || 0.5), 0)}% sure of the best`),
        h("div", { class: "up-candidates" }, ...up.candidates.slice(0, 3).map((c, i) => upCandidateFigure(s, c, i, status, onPicked))),
        status);
    }));
}
