/* Omnidata dashboard: plain JavaScript, no build step. Talks to the JSON API with the token kept in
   sessionStorage, and follows progress over server-sent events (EventSource cannot set headers, so the
   SSE routes take the token as ?token=). Every text from the server goes into the DOM as text, never HTML. */
"use strict";

const TOKEN_KEY = "omnidata.token";
const API = new URL("..", document.baseURI).pathname.replace(/\/$/, ""); // the API root ("" when at /ui/)
const state = { view: null, sources: [], timers: [] };

// ------------------------------------------------------------------------------------------ helpers

function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "class") el.className = v;
    else if (k === "dataset") Object.assign(el.dataset, v);
    else if (k === "style") el.style.cssText = v;  // through the CSSOM: the CSP refuses style attributes
    else el.setAttribute(k, v === true ? "" : String(v));
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

function svg(tag, attrs, ...children) {
  const el = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs || {})) el.setAttribute(k, String(v));
  for (const c of children.flat()) if (c) el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return el;
}

const token = () => sessionStorage.getItem(TOKEN_KEY);

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

async function api(path, opts = {}) {
  const headers = Object.assign({ Authorization: `Bearer ${token()}` }, opts.headers || {});
  let body = opts.body;
  if (body && !(body instanceof FormData) && typeof body !== "string") {
    body = JSON.stringify(body);
    headers["Content-Type"] = "application/json";
  }
  const r = await fetch(API + path, { method: opts.method || "GET", headers, body });
  if (r.status === 401) { logout("Your token was refused; log in again."); throw new ApiError(401, "unauthorized"); }
  if (r.status === 204) return null;
  const ctype = r.headers.get("content-type") || "";
  const data = ctype.includes("json") ? await r.json() : await r.text();
  if (!r.ok) throw new ApiError(r.status, (data && data.detail) || `HTTP ${r.status}`);
  return data;
}

function fmtNum(x, digits = 1) {
  if (x === null || x === undefined) return "–";
  return Number(x).toLocaleString(undefined, { maximumFractionDigits: digits });
}

function fmtDuration(s) {
  if (s === null || s === undefined) return "–";
  s = Math.round(s);
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${s % 60} s`;
  return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
}

function pct(f) { return `${(100 * (f || 0)).toFixed(1)}%`; }

function bar(fraction, cls = "", label = null) {
  const f = Math.max(0, Math.min(1, fraction || 0));
  return h("div", { class: `bar ${cls}`, role: "progressbar", "aria-valuenow": (100 * f).toFixed(1),
                    "aria-valuemin": 0, "aria-valuemax": 100, dataset: { fraction: f.toFixed(6) } },
    h("div", { class: "fill", style: `width:${(100 * f).toFixed(2)}%` }),
    h("span", { class: "bar-label" }, label === null ? pct(f) : label));
}

function badge(s) { return h("span", { class: `badge state-${s}` }, s); }

function flash(msg, kind = "error") {
  let box = document.getElementById("flash");
  if (!box) { box = h("div", { id: "flash" }); document.getElementById("app").prepend(box); }
  box.replaceChildren(h("div", { class: `flash ${kind}`, role: "status" }, msg,
    h("button", { class: "link", "aria-label": "dismiss", onclick: () => box.replaceChildren() }, "×")));
}

function closeLive() {
  for (const es of state.sources) es.close();
  state.sources = [];
  for (const t of state.timers) clearInterval(t);
  state.timers = [];
  document.getElementById("live").hidden = true;
}

function listen(path, onJob, onDeleted) {
  const url = `${API}${path}?token=${encodeURIComponent(token())}`;
  const es = new EventSource(url);
  const live = document.getElementById("live");
  es.addEventListener("open", () => { live.hidden = false; live.classList.remove("off"); });
  es.addEventListener("error", () => { live.classList.add("off"); });
  es.addEventListener("job", (e) => onJob(JSON.parse(e.data)));
  if (onDeleted) es.addEventListener("deleted", (e) => onDeleted(JSON.parse(e.data)));
  es.addEventListener("end", () => es.close());  // a finished job's stream closes: do not reconnect
  state.sources.push(es);
  return es;
}

function every(ms, fn) { state.timers.push(setInterval(fn, ms)); }

// ------------------------------------------------------------------------------------------ login

function logout(message) {
  sessionStorage.removeItem(TOKEN_KEY);
  closeLive();
  location.hash = "#/login";
  if (message) setTimeout(() => flash(message), 0);
}

function viewLogin() {
  const input = h("input", { id: "login-token", type: "password", autocomplete: "off", placeholder: "API token",
                             required: true, size: 40 });
  const err = h("p", { class: "error", id: "login-error" });
  const form = h("form", { class: "card login", onsubmit: async (e) => {
    e.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, input.value.trim());
    try {
      const r = await fetch(`${API}/jobs?limit=1`, { headers: { Authorization: `Bearer ${token()}` } });
      if (!r.ok) throw new Error((await r.json()).detail || `HTTP ${r.status}`);
      location.hash = "#/jobs";
    } catch (ex) {
      sessionStorage.removeItem(TOKEN_KEY);
      err.textContent = `Login failed: ${ex.message}`;
    }
  } },
    h("h1", {}, "Log in"),
    h("p", {}, "Paste your API token. It stays in this browser tab only (sessionStorage)."),
    h("label", {}, "Token ", input),
    h("button", { id: "login-submit", type: "submit" }, "Log in"), err);
  return form;
}

// ------------------------------------------------------------------------------------------ jobs page

function cueBars(cues) {
  return h("div", { class: "cues" }, Object.entries(cues).map(([cue, c]) =>
    h("div", { class: "cue", title: `${cue}: ${c.done}/${c.total} done` + (c.by_state.failed ? `, ${c.by_state.failed} failed` : "") },
      h("span", { class: "cue-name" }, cue), bar(c.fraction, c.by_state.failed ? "small warn" : "small",
        `${c.done}/${c.total}`))));
}

function actionButtons(job, after) {
  const act = async (name, method = "POST") => {
    try {
      if (name === "delete") {
        if (!confirm(`Delete job ${job.id} and all its outputs?`)) return;
        await api(`/jobs/${job.id}`, { method: "DELETE" });
      } else {
        await api(`/jobs/${job.id}/${name}`, { method });
      }
      if (after) after(name);
    } catch (ex) { flash(`${name} failed: ${ex.message}`); }
  };
  const s = job.state;
  const fin = ["done", "failed", "cancelled"].includes(s);
  return h("div", { class: "actions" },
    s === "running" && h("button", { class: "act-pause", onclick: () => act("pause") }, "Pause"),
    s === "paused" && h("button", { class: "act-resume", onclick: () => act("resume") }, "Resume"),
    !fin && h("button", { class: "act-cancel", onclick: () => act("cancel") }, "Cancel"),
    (job.progress.by_state.failed > 0 && s !== "cancelled") && h("button", { class: "act-retry", onclick: () => act("retry") }, "Retry failed"),
    h("button", { class: "act-delete danger", onclick: () => act("delete") }, "Delete"));
}

function jobRow(job, refresh) {
  const p = job.progress;
  return h("tr", { dataset: { jobId: job.id, state: job.state } },
    h("td", {}, h("a", { href: `#/jobs/${job.id}` }, `#${job.id} ${job.name}`)),
    h("td", {}, badge(job.state), job.error && h("div", { class: "error small-text" }, job.error)),
    h("td", { class: "progress-cell" }, bar(p.fraction, "overall", `${pct(p.fraction)} (${p.finished}/${p.total})`),
      cueBars(job.cues)),
    h("td", { class: "num" }, p.throughput_per_s === null ? "–" : `${fmtNum(p.throughput_per_s, 2)} tasks/s`,
      h("div", { class: "muted" }, p.labels_per_s === null ? "" : `${fmtNum(p.labels_per_s, 2)} labels/s`)),
    h("td", { class: "num" }, job.state === "running" ? fmtDuration(p.eta_s) : "–"),
    h("td", {}, actionButtons(job, refresh)));
}

function newJobForm(spaces, onCreated) {
  const spaceSel = h("select", { id: "job-space", name: "space", required: true },
    spaces.map((s) => h("option", { value: s.id }, `${s.name} (#${s.id}, ${fmtNum(s.face_count, 0)} faces)`)));
  const cueBox = h("div", { class: "cue-picks", id: "job-cues" });
  const fillCues = () => {
    const sp = spaces.find((s) => String(s.id) === spaceSel.value);
    cueBox.replaceChildren(...(sp ? sp.supported_cues : []).map((c) =>
      h("label", { class: "check" }, h("input", { type: "checkbox", name: "cue", value: c,
        checked: ["rgb", "normal", "depth_zbuffer"].includes(c) }), c)));
  };
  spaceSel.addEventListener("change", fillCues);
  fillCues();
  const num = (id, value, min, max) => h("input", { id, type: "number", value, min, max, required: true });
  const points = num("job-points", 10, 1, 10000000), res = num("job-resolution", 128, 16, 4096);
  const seed = num("job-seed", 0, 0, 2 ** 53), name = h("input", { id: "job-name", value: "omnidata", required: true });
  const mode = h("select", { id: "job-camera-mode" }, h("option", { value: "object" }, "object (orbit)"),
    h("option", { value: "generate" }, "generate (in free space)"));
  const err = h("p", { class: "error" });
  return h("form", { class: "card", id: "new-job", onsubmit: async (e) => {
    e.preventDefault();
    err.textContent = "";
    const cues = [...cueBox.querySelectorAll("input:checked")].map((i) => i.value);
    const spec = { name: name.value, seed: Number(seed.value), points: { count: Number(points.value) },
                   views: { resolution: Number(res.value) }, cameras: { mode: mode.value } };
    if (cues.length) spec.cues = cues;
    try {
      const job = await api("/jobs", { method: "POST", body: { space_ids: [Number(spaceSel.value)], spec } });
      flash(`Job #${job.id} created.`, "ok");
      onCreated(job);
    } catch (ex) { err.textContent = ex.message; }
  } },
    h("h2", {}, "New job"),
    spaces.length ? null : h("p", { class: "muted" }, "Upload a space first."),
    h("div", { class: "grid" },
      h("label", {}, "Space", spaceSel), h("label", {}, "Name", name), h("label", {}, "Cameras", mode),
      h("label", {}, "Points", points), h("label", {}, "Resolution (px)", res), h("label", {}, "Seed", seed)),
    h("fieldset", {}, h("legend", {}, "Cues"), cueBox),
    h("button", { type: "submit", id: "job-submit", disabled: !spaces.length }, "Create job"), err);
}

function uploadForm(onUploaded) {
  const file = h("input", { id: "upload-file", type: "file", required: true, accept: ".ply,.obj,.glb,.gltf,.zip" });
  const name = h("input", { id: "upload-name", placeholder: "default: file name" });
  const up = h("select", { id: "upload-up" }, ["auto", "+z", "+y", "-z", "-y", "+x", "-x"].map((a) => h("option", { value: a }, a)));
  const scale = h("input", { id: "upload-scale", type: "text", value: "auto", title: "metres per source unit, or auto" });
  const capture = h("input", { id: "upload-capture", type: "file", accept: ".zip", title: "optional: the scan's posed photos (a .zip)" });
  const status = h("p", { class: "muted" });
  const btn = h("button", { type: "submit", id: "upload-submit" }, "Upload");
  return h("form", { class: "card", id: "upload", onsubmit: async (e) => {
    e.preventDefault();
    const fd = new FormData();
    fd.append("file", file.files[0]);
    if (capture.files.length) fd.append("capture", capture.files[0]);
    if (name.value) fd.append("name", name.value);
    fd.append("up_axis", up.value);
    fd.append("unit_scale", scale.value);
    btn.disabled = true;
    status.className = "muted";
    status.textContent = "Uploading and validating…";
    try {
      const s = await api("/spaces", { method: "POST", body: fd });
      status.textContent = `Space "${s.name}" registered: ${fmtNum(s.face_count, 0)} faces` +
        (s.has_texture ? ", textured" : "") + ". " + frameText(s.frame) +
        (s.frame && s.frame.capture ? ` Capture: ${s.frame.capture.format}, ${s.frame.capture.frames} frames.` : "");
      onUploaded(s);
    } catch (ex) { status.className = "error"; status.textContent = ex.message; }
    btn.disabled = false;
  } },
    h("h2", {}, "Upload a space"),
    h("p", { class: "muted" }, "A mesh (.ply, .obj, .glb, .gltf), a point cloud (.ply, .xyz, .pts) or a .zip with the mesh and its textures."),
    h("div", { class: "grid" }, h("label", {}, "File", file), h("label", {}, "Name", name),
      h("label", {}, "Up axis", up), h("label", {}, "Metres per unit", scale),
      h("label", {}, "Capture (.zip, optional)", capture)),
    btn, status);
}

// What ingest found about a space's frame (SpaceRead.frame / JobSpaceRead.frame): up, how, how sure; units.
function frameText(frame) {
  if (!frame || !frame.up) return "";
  const u = frame.up;
  let text = `Up [${u.source_direction.map((x) => fmtNum(x, 3)).join(", ")}] (${u.method}, ${u.confidence} confidence` +
    (u.probability !== undefined && u.probability !== null ? `, ${fmtNum(100 * u.probability, 0)}% sure` : "") + ")";
  if (u.ambiguous) text += u.candidates && u.candidates.length > 1 ? "; ambiguous: pick its up above before a job" : "; ambiguous";
  if (frame.units) text += `; units: ${frame.units.unit} (x${frame.units.unit_scale})`;
  if (frame.reconstruction) text += `; meshed from ${fmtNum(frame.reconstruction.point_count, 0)} points`;
  return text + ".";
}

async function viewJobs(root) {
  const table = h("tbody", { id: "jobs-body" });
  const total = h("span", { class: "muted" });
  const forms = h("div", { class: "forms" });
  root.append(h("section", {},
    h("div", { class: "row" }, h("h1", {}, "Jobs"), total),
    h("table", { class: "jobs" }, h("thead", {}, h("tr", {}, h("th", {}, "Job"), h("th", {}, "State"),
      h("th", {}, "Progress"), h("th", {}, "Throughput"), h("th", {}, "ETA"), h("th", {}, ""))), table)), forms);
  const rows = new Map();
  const refresh = async () => {
    const page = await api("/jobs?limit=100");
    total.textContent = `${page.total} job(s)`;
    rows.clear();
    table.replaceChildren(...page.items.map((j) => { const tr = jobRow(j, refresh); rows.set(j.id, tr); return tr; }));
    if (!page.items.length) table.append(h("tr", {}, h("td", { colspan: 6, class: "muted" }, "No jobs yet.")));
  };
  const jobFormSlot = h("div", {});
  const frameSlot = h("div", {});
  const refreshJobForm = async (selectId) => {
    const spaces = (await api("/spaces?limit=1000")).items;
    frameSlot.replaceChildren(...[needsFramePanel(spaces, () => refreshJobForm())].filter(Boolean));
    const form = newJobForm(spaces, refresh);
    if (selectId) { form.querySelector("#job-space").value = String(selectId); form.querySelector("#job-space").dispatchEvent(new Event("change")); }
    jobFormSlot.replaceChildren(form);
  };
  forms.replaceChildren(frameSlot, jobFormSlot, uploadForm((space) => refreshJobForm(space.id)));
  await Promise.all([refresh(), refreshJobForm()]);
  listen("/events", (ev) => {
    const tr = rows.get(ev.id);
    if (!tr) { refresh(); return; }
    const job = Object.assign({}, ev, { space_ids: [] });
    const fresh = jobRow(job, refresh);
    rows.set(ev.id, fresh);
    tr.replaceWith(fresh);
  }, (ev) => { const tr = rows.get(ev.id); if (tr) { tr.remove(); rows.delete(ev.id); } });
}

// ------------------------------------------------------------------------------------------ job page

function planPlot(space) {
  const W = 420, H = 420, pad = 16;
  const xs = [], ys = [];
  for (const c of space.cameras) { xs.push(c[0]); ys.push(c[1]); }
  for (const p of space.points) { xs.push(p[0]); ys.push(p[1]); }
  if (space.bounds) { xs.push(space.bounds[0][0], space.bounds[1][0]); ys.push(space.bounds[0][1], space.bounds[1][1]); }
  if (!xs.length) return h("p", { class: "muted" }, "No plan yet.");
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const s = Math.min((W - 2 * pad) / Math.max(x1 - x0, 1e-6), (H - 2 * pad) / Math.max(y1 - y0, 1e-6));
  const X = (x) => pad + (x - x0) * s, Y = (y) => H - pad - (y - y0) * s; // +Y up on screen
  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "plot", role: "img",
                         "aria-label": `top-down plan of ${space.name}` });
  if (space.bounds) {
    const [b0, b1] = space.bounds;
    g.append(svg("rect", { x: X(b0[0]), y: Y(b1[1]), width: (b1[0] - b0[0]) * s, height: (b1[1] - b0[1]) * s,
                           class: "bounds" }));
  }
  const edges = svg("g", { class: "edges" });
  for (const [p, c] of space.views.slice(0, 4000)) {
    const P = space.points[p], C = space.cameras[c];
    if (P && C) edges.append(svg("line", { x1: X(C[0]), y1: Y(C[1]), x2: X(P[0]), y2: Y(P[1]) }));
  }
  g.append(edges);
  for (const p of space.points) g.append(svg("circle", { cx: X(p[0]), cy: Y(p[1]), r: 2.2, class: "point" },
    svg("title", {}, `point (${p[0].toFixed(2)}, ${p[1].toFixed(2)}, ${p[2].toFixed(2)}) m, ${p[3]} views`)));
  for (const c of space.cameras) {
    const yaw = c[3], len = 9, cx = X(c[0]), cy = Y(c[1]);
    const tip = [cx + len * Math.cos(yaw), cy - len * Math.sin(yaw)];
    const l = [cx + 4 * Math.cos(yaw + 2.5), cy - 4 * Math.sin(yaw + 2.5)];
    const r = [cx + 4 * Math.cos(yaw - 2.5), cy - 4 * Math.sin(yaw - 2.5)];
    g.append(svg("polygon", { points: `${tip} ${l} ${r}`, class: "camera" },
      svg("title", {}, `camera (${c[0].toFixed(2)}, ${c[1].toFixed(2)}, ${c[2].toFixed(2)}) m`)));
  }
  return h("figure", { class: "plan" }, g, h("figcaption", {},
    `${space.name}: ${space.cameras.length} cameras (triangles), ${space.points.length} points (dots)` +
    (space.truncated ? " – truncated" : "") + "; top-down, metres, +x right, +y up"));
}

// A posed capture found with a space (frame.capture) and, once planned, its views' alignment (plan_summary
// capture_plan): frames, intrinsics, lens, problems, and a histogram of the photo/geometry alignment scores.
function captureCard(name, capture, planned) {
  const focal = capture.focal_px ? `focal ${capture.focal_px.map((x) => fmtNum(x, 1)).join(" / ")} px (min/median/max)` : "no intrinsics";
  const sizes = capture.image_sizes.map((s) => s.join("x")).join(", ") || "no photos";
  const lines = [
    h("p", {}, `${name}: ${capture.format} capture, ${capture.frames} frames${capture.has_photos ? "" : " (poses only)"};` +
      ` ${sizes}; ${focal}; lens ${capture.distortion.join(", ")}` +
      (capture.up_angle_deg === null || capture.up_angle_deg === undefined ? "" : `; cameras' up ${fmtNum(capture.up_angle_deg, 1)}° from the scan's`)),
  ];
  if (capture.problems) lines.push(h("p", { class: "error" }, `${capture.problems} problem(s): ${capture.problem_messages.slice(0, 3).join("; ")}`));
  const al = planned && planned.alignment;
  if (al && al.histogram) lines.push(alignmentChart(al));
  return h("div", { class: "capture", dataset: { space: name } }, ...lines);
}

function alignmentChart(al) {
  const W = 420, H = 140, pad = 24;
  const counts = al.histogram.counts, edges = al.histogram.edges;
  const max = Math.max(1, ...counts);
  const bw = (W - 2 * pad) / counts.length;
  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "chart alignment", role: "img", "aria-label": "alignment score histogram" });
  g.append(svg("line", { x1: pad, y1: H - pad, x2: W - pad, y2: H - pad, class: "axis" }));
  counts.forEach((c, i) => {
    const bh = (H - 2 * pad) * (c / max);
    g.append(svg("rect", { x: pad + i * bw + 0.5, y: H - pad - bh, width: Math.max(bw - 1, 0.5), height: bh },
      svg("title", {}, `${c} views scored ${fmtNum(edges[i], 2)}–${fmtNum(edges[i + 1], 2)}`)));
  });
  g.append(svg("text", { x: pad, y: 14, class: "chart-label" },
    `alignment of ${al.scored} views: median ${fmtNum(al.median, 2)} (~1 is chance)`));
  g.append(svg("text", { x: pad, y: H - 6, class: "chart-label" }, fmtNum(edges[0], 2)));
  g.append(svg("text", { x: W - pad, y: H - 6, class: "chart-label", "text-anchor": "end" }, fmtNum(edges[edges.length - 1], 2)));
  return g;
}

function throughputChart(tp) {
  const W = 420, H = 140, pad = 24;
  const n = tp.buckets.length;
  if (!n) return h("p", { class: "muted" }, "No finished tasks yet.");
  const max = Math.max(1, ...tp.buckets.map((b) => b.done));
  const bw = (W - 2 * pad) / n;
  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "chart", role: "img", "aria-label": "throughput over time" });
  g.append(svg("line", { x1: pad, y1: H - pad, x2: W - pad, y2: H - pad, class: "axis" }));
  tp.buckets.forEach((b, i) => {
    const bh = (H - 2 * pad) * (b.done / max);
    g.append(svg("rect", { x: pad + i * bw + 0.5, y: H - pad - bh, width: Math.max(bw - 1, 0.5), height: bh },
      svg("title", {}, `${new Date(b.t).toLocaleTimeString()}: ${b.done} tasks (${(b.done / tp.bucket_s).toFixed(2)}/s)`)));
  });
  g.append(svg("text", { x: pad, y: 14, class: "chart-label" }, `peak ${(max / tp.bucket_s).toFixed(2)} tasks/s`));
  g.append(svg("text", { x: W - pad, y: H - 6, class: "chart-label", "text-anchor": "end" }, `${tp.bucket_s} s buckets`));
  return g;
}

function outputTile(cue, link) {
  if (!link) return h("div", { class: "tile missing" }, h("span", {}, cue));
  // Previews are readable renderings of every cue (colour maps, palettes, drawn JSON); the link opens the raw file.
  const src = link.preview_url || (link.content_type === "image/png" ? link.url : null);
  return h("a", { class: "tile", href: link.url, target: "_blank", rel: "noopener", title: `${cue}: ${link.key}` },
    src ? h("img", { src, alt: cue, loading: "lazy" }) : h("div", { class: "file" }, link.key.split(".").pop()),
    h("span", {}, cue));
}

async function viewJob(root, id) {
  const head = h("div", { class: "card", id: "job-head" });
  const plot = h("div", { class: "card", id: "job-plan" }, h("h2", {}, "Plan"));
  const chart = h("div", { class: "card", id: "job-throughput" }, h("h2", {}, "Throughput"));
  const gallery = h("div", { class: "card", id: "job-gallery" });
  const failures = h("div", { class: "card", id: "job-failures" });
  root.append(h("p", {}, h("a", { href: "#/jobs" }, "← all jobs")), head,
    h("div", { class: "two" }, plot, chart), gallery, failures);
  let job = await api(`/jobs/${id}`);
  let galleryOffset = 0, lastDone = -1, lastFailed = -1;

  const renderHead = () => {
    const p = job.progress;
    head.replaceChildren(...[
      h("div", { class: "row" }, h("h1", {}, `Job #${job.id} ${job.name}`), badge(job.state)),
      job.error && h("p", { class: "error" }, job.error),
      bar(p.fraction, "overall big", `${pct(p.fraction)} (${p.finished}/${p.total} tasks)`),
      h("p", { class: "stats" },
        `throughput ${p.throughput_per_s === null ? "–" : fmtNum(p.throughput_per_s, 2) + " tasks/s"}` +
        ` · ${p.labels_per_s === null ? "–" : fmtNum(p.labels_per_s, 2) + " labels/s"}` +
        ` · ETA ${job.state === "running" ? fmtDuration(p.eta_s) : "–"}` +
        ` · pending ${p.by_state.pending}, queued ${p.by_state.queued}, running ${p.by_state.running},` +
        ` done ${p.by_state.done}, failed ${p.by_state.failed}, cancelled ${p.by_state.cancelled}`),
      cueBars(job.cues),
      ...(job.spaces || []).filter((sp) => sp.frame).map((sp) =>
        h("p", { class: sp.frame.up && sp.frame.up.confidence === "low" ? "error" : "muted" },
          `${sp.name}: ${frameText(sp.frame)}`)),
      ...(job.spaces || []).filter((sp) => sp.frame && sp.frame.capture).map((sp) =>
        captureCard(sp.name, sp.frame.capture, ((job.plan_summary || {}).spaces || {})[sp.name]?.capture_plan)),
      actionButtons(job, (name) => { if (name === "delete") location.hash = "#/jobs"; else reload(); }),
    ].filter(Boolean));
  };
  const reload = async () => { job = Object.assign(job, await api(`/jobs/${id}`)); renderHead(); };

  const renderPlan = async () => {
    const plan = await api(`/jobs/${id}/plan?max_items=5000`);
    plot.replaceChildren(h("h2", {}, "Plan"), ...(plan.spaces.length ? plan.spaces.map(planPlot) : [h("p", { class: "muted" }, "No plan yet.")]));
  };
  const renderChart = async () => {
    const tp = await api(`/jobs/${id}/throughput?buckets=40`);
    chart.replaceChildren(h("h2", {}, "Throughput"), throughputChart(tp));
  };
  const renderGallery = async () => {
    const page = await api(`/jobs/${id}/views?complete=true&urls=true&limit=8&offset=${galleryOffset}`);
    const pager = h("div", { class: "row" },
      h("button", { disabled: galleryOffset === 0, onclick: () => { galleryOffset = Math.max(0, galleryOffset - 8); renderGallery(); } }, "‹ prev"),
      h("span", { class: "muted" }, page.total ? `views ${galleryOffset + 1}–${galleryOffset + page.items.length} of ${page.total} finished` : "no finished views yet"),
      h("button", { disabled: galleryOffset + 8 >= page.total, onclick: () => { galleryOffset += 8; renderGallery(); } }, "next ›"));
    gallery.replaceChildren(h("h2", {}, "Finished views"), pager,
      ...page.items.map((v) => h("div", { class: "view-row", dataset: { point: v.point, view: v.view } },
        h("div", { class: "view-label" }, `${v.space} · point ${v.point} · view ${v.view}`,
          h("div", { class: "muted" }, `fov ${v.fov_deg.toFixed(1)}°, ${v.resolution}px`)),
        h("div", { class: "tiles" }, Object.entries(v.outputs || {}).map(([cue, link]) => outputTile(cue, link))))));
  };
  const renderFailures = async () => {
    const page = await api(`/jobs/${id}/tasks?state=failed&limit=20`);
    failures.replaceChildren(h("h2", {}, `Failures (${page.total})`),
      page.total ? h("table", { class: "failures" }, h("thead", {}, h("tr", {}, h("th", {}, "Task"), h("th", {}, "Cue"),
        h("th", {}, "Point/view"), h("th", {}, "Attempts"), h("th", {}, "Error"))),
        h("tbody", {}, page.items.map((t) => h("tr", {}, h("td", {}, t.id), h("td", {}, t.cue),
          h("td", {}, `${t.point}/${t.view}`), h("td", {}, t.attempts), h("td", {}, h("pre", {}, t.error || "")))))) :
        h("p", { class: "muted" }, "No failed tasks."));
  };

  renderHead();
  await Promise.all([renderPlan(), renderChart(), renderGallery(), renderFailures()]);
  lastDone = job.progress.by_state.done;
  lastFailed = job.progress.by_state.failed;
  let planned = job.progress.total > 0;
  listen(`/jobs/${id}/events`, (ev) => {
    Object.assign(job, ev);
    renderHead();
    if (!planned && ev.progress.total > 0) { planned = true; renderPlan(); }
    if (ev.progress.by_state.done !== lastDone) { lastDone = ev.progress.by_state.done; renderGallery(); }
    if (ev.progress.by_state.failed !== lastFailed) { lastFailed = ev.progress.by_state.failed; renderFailures(); }
  }, () => { flash(`Job ${id} was deleted.`); location.hash = "#/jobs"; });
  every(5000, () => { if (job.state === "running" || job.state === "paused") renderChart(); });
}

// ------------------------------------------------------------------------------------------ workers page

async function viewWorkers(root) {
  const body = h("tbody", { id: "workers-body" });
  const total = h("span", { class: "muted" });
  root.append(h("section", {}, h("div", { class: "row" }, h("h1", {}, "Workers"), total),
    h("table", { class: "workers" }, h("thead", {}, h("tr", {}, ...["Worker", "Host", "Queues", "Status", "Heartbeat",
      "Current task", "Labels/s", "Tasks done"].map((t) => h("th", {}, t)))), body)));
  const refresh = async () => {
    const page = await api("/workers?limit=500");
    total.textContent = `${page.items.filter((w) => w.alive).length} alive of ${page.total}`;
    body.replaceChildren(...page.items.map((w) => h("tr", { dataset: { workerId: w.id } },
      h("td", {}, w.id), h("td", {}, w.host), h("td", {}, w.queues.join(", ")),
      h("td", {}, badge(w.alive ? "alive" : "stale")), h("td", { class: "num" }, `${fmtNum(w.heartbeat_age_s, 1)} s ago`),
      h("td", {}, w.current_task ? h("a", { href: `#/jobs/${w.current_task.job_id}` },
        `job ${w.current_task.job_id}: ${w.current_task.cue} p${w.current_task.point}/v${w.current_task.view}`) :
        (w.busy ? "busy (another tenant)" : "idle")),
      h("td", { class: "num" }, fmtNum(w.labels_per_s, 2)), h("td", { class: "num" }, fmtNum(w.tasks_done, 0)))));
    if (!page.items.length) body.append(h("tr", {}, h("td", { colspan: 8, class: "muted" }, "No workers have reported yet.")));
  };
  await refresh();
  every(3000, refresh);
}

// ------------------------------------------------------------------------------------------ router

async function route() {
  closeLive();
  const root = document.getElementById("app");
  root.replaceChildren(h("div", { id: "flash" }));
  const hash = location.hash || "#/jobs";
  const authed = !!token();
  document.getElementById("nav").hidden = !authed;
  document.getElementById("logout").hidden = !authed;
  if (!authed && hash !== "#/login") { location.hash = "#/login"; return; }
  for (const a of document.querySelectorAll("[data-nav]")) a.classList.toggle("active", hash.startsWith(`#/${a.dataset.nav}`));
  try {
    let m;
    if (hash === "#/login") root.append(viewLogin());
    else if (hash === "#/workers") await viewWorkers(root);
    else if (hash === "#/designer") await viewDesigner(root);
    else if ((m = hash.match(/^#\/jobs\/(\d+)$/))) await viewJob(root, Number(m[1]));
    else await viewJobs(root);
  } catch (ex) {
    if (ex.status !== 401) flash(ex.message);
  }
}

document.getElementById("logout").addEventListener("click", () => logout());
window.addEventListener("hashchange", route);
route();
