/* The designer page (#/designer): pick spaces, edit every JobSpec knob in a form built from the spec's
   JSON schema or as YAML (each updates the other through the server, which validates both), and see the
   plan's top and side views, the histograms of its view distributions and a few small previews within
   seconds. Two specs, A and B, keep their own results; their histograms are drawn overlaid. Loaded before
   app.js; uses its helpers (h, svg, api, fmtNum) only when called. */
"use strict";

const DESIGN_CUES = ["rgb", "depth_zbuffer", "normal", "segment_unsup2d"];
const DIST_LABELS = { fov_deg: "field of view (°)", pitch_deg: "pitch (°)", roll_deg: "roll (°)",
  height_m: "camera height (m)", distance_m: "distance to the point (m)", obliqueness_deg: "obliqueness (°)",
  views_per_point: "views per point" };
// 500 views on a room
const DESIGN_START = { points: { count: 100, max_views: 5 }, views: { resolution: 256 } };

// ------------------------------------------------------------------------------------------ schema form

function resolveRef(schema, node) {
  return node && node.$ref ? schema.$defs[node.$ref.split("/").pop()] : node;
}

// {kind: number | integer | boolean | enum | string | json | object, nullable}
function knobKind(node) {
  const options = node.anyOf || [node];
  const real = options.filter((o) => o.type !== "null");
  const nullable = real.length < options.length;
  if (real.length === 1 && real[0].$ref) return { kind: "object", nullable, ref: real[0] };
  if (real.length !== 1) return { kind: "json", nullable };  // e.g. a number or "auto"
  const o = real[0];
  if (o.enum) return { kind: "enum", nullable, values: o.enum };
  if (o.const !== undefined) return { kind: "enum", nullable, values: [o.const] };
  if (["number", "integer", "boolean", "string"].includes(o.type)) return { kind: o.type, nullable };
  return { kind: "json", nullable };
}

function getPath(obj, path) {
  return path.reduce((o, k) => (o && typeof o === "object" ? o[k] : undefined), obj);
}

function setPath(obj, path, value) {
  let o = obj;
  for (const k of path.slice(0, -1)) o = (o[k] = o[k] && typeof o[k] === "object" ? o[k] : {});
  if (value === undefined) delete o[path[path.length - 1]]; else o[path[path.length - 1]] = value;
}

function knobInput(path, node, kind, onChange) {
  const id = `knob-${path.join("-")}`;
  const read = (el) => {
    if (kind.kind === "boolean") return el.checked;
    const raw = el.value.trim();
    if (raw === "") return kind.nullable ? null : undefined;
    if (kind.kind === "number" || kind.kind === "integer") return Number(raw);
    if (kind.kind === "json") { try { return JSON.parse(raw); } catch { return raw; } }
    return raw;
  };
  let el;
  if (kind.kind === "boolean") el = h("input", { id, type: "checkbox" });
  else if (kind.kind === "enum") {
    el = h("select", { id }, kind.nullable ? h("option", { value: "" }, "none") : null,
      kind.values.map((v) => h("option", { value: v }, v)));
  } else {
    const numeric = kind.kind === "number" || kind.kind === "integer";
    el = h("input", { id, type: numeric ? "number" : "text", step: "any",
                      placeholder: kind.nullable ? "none" : "" });
  }
  el.dataset.path = JSON.stringify(path);
  el.dataset.kind = kind.kind;
  const box = kind.kind === "boolean";
  el.addEventListener(box || kind.kind === "enum" ? "change" : "input", () => onChange(path, read(el)));
  return h("label", { class: box ? "check" : "", title: node.description || "" },
    box ? el : null, path[path.length - 1].replace(/_/g, " "), box ? null : el);
}

function specForm(schema, onChange, node = schema, path = [], depth = 0) {
  const simple = [], nested = [];
  for (const [name, prop] of Object.entries(node.properties || {})) {
    const kind = knobKind(prop);
    if (kind.kind === "object") {
      const sub = resolveRef(schema, kind.ref);
      const open = depth === 0 && ["cameras", "points", "views"].includes(name);
      nested.push(h("details", { class: "knobs", open },
        h("summary", {}, name), specForm(schema, onChange, sub, [...path, name], depth + 1)));
    } else simple.push(knobInput([...path, name], prop, kind, onChange));
  }
  return h("div", { class: "knob-group" }, h("div", { class: "grid" }, simple), nested);
}

function schemaDefaults(schema, node = schema) {  // the whole default spec, nested objects included
  const out = {};
  for (const [name, prop] of Object.entries(node.properties || {})) {
    const kind = knobKind(prop);
    if (prop.default !== undefined) out[name] = prop.default;
    else if (kind.kind === "object") out[name] = schemaDefaults(schema, resolveRef(schema, kind.ref));
  }
  return out;
}

function fillForm(form, defaults, spec) {
  for (const el of form.querySelectorAll("[data-path]")) {
    if (el === document.activeElement) continue;  // do not overwrite what the person is typing
    const path = JSON.parse(el.dataset.path);
    let value = getPath(spec, path);
    if (value === undefined) value = getPath(defaults, path);
    if (el.dataset.kind === "boolean") el.checked = !!value;
    else if (value === null || value === undefined) el.value = "";
    else if (el.dataset.kind === "json" && typeof value !== "string") el.value = JSON.stringify(value);
    else el.value = String(value);
  }
}

// ------------------------------------------------------------------------------------------ drawings

function designPlot(space, axes, slot) {  // axes [0, 1]: top-down (x, y); [0, 2]: side (x, z)
  const W = 300, H = axes[1] === 1 ? 240 : 130, pad = 10;
  const [b0, b1] = space.bounds, [i, j] = axes;
  const s = Math.min((W - 2 * pad) / Math.max(b1[i] - b0[i], 1e-6),
                     (H - 2 * pad) / Math.max(b1[j] - b0[j], 1e-6));
  const X = (p) => pad + (p[i] - b0[i]) * s, Y = (p) => H - pad - (p[j] - b0[j]) * s;
  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: `plot design-plot slot-${slot}`, role: "img",
    "aria-label": `${axes[1] === 1 ? "top-down" : "side"} view of ${space.name}` });
  g.append(svg("rect", { x: X(b0), y: Y(b1), width: (b1[i] - b0[i]) * s, height: (b1[j] - b0[j]) * s,
                         class: "bounds" }));
  const edges = svg("g", { class: "edges" });
  for (const [p, c] of space.lines) {
    const P = space.points[p], C = space.cameras[c];
    edges.append(svg("line", { x1: X(C), y1: Y(C), x2: X(P), y2: Y(P) }));
  }
  g.append(edges);
  for (const p of space.points) g.append(svg("circle", { cx: X(p), cy: Y(p), r: 1.6, class: "point" }));
  for (const c of space.cameras) {
    g.append(svg("rect", { x: X(c) - 2, y: Y(c) - 2, width: 4, height: 4, class: "camera" }));
  }
  return g;
}

// series: [{slot, histogram}], each drawn as fractions of its own total so that A and B compare
function overlayHistogram(name, series) {
  const W = 260, H = 120, pad = 18;
  const edges = series[0].histogram.edges, bins = edges.length - 1;
  const fracs = series.map((s) => { const n = s.histogram.counts.reduce((a, b) => a + b, 0) || 1;
    return s.histogram.counts.map((c) => c / n); });
  const max = Math.max(1e-9, ...fracs.flat()), bw = (W - 2 * pad) / bins;
  const label = DIST_LABELS[name] || name;
  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "chart hist", role: "img", "aria-label": label });
  g.dataset.name = name;
  series.forEach((s, k) => {
    g.dataset[`counts${s.slot.toUpperCase()}`] = s.histogram.counts.join(",");
    const grp = svg("g", { class: `series series-${s.slot}` });
    fracs[k].forEach((f, b) => {
      if (!f) return;
      const bh = (H - 2 * pad) * (f / max);
      grp.append(svg("rect", { x: pad + b * bw, y: H - pad - bh, width: Math.max(bw - 0.5, 0.5), height: bh },
        svg("title", {}, `${s.slot.toUpperCase()}: ${s.histogram.counts[b]} in ` +
          `${fmtNum(edges[b], 2)}–${fmtNum(edges[b + 1], 2)}`)));
    });
    g.append(grp);
  });
  g.append(svg("line", { x1: pad, y1: H - pad, x2: W - pad, y2: H - pad, class: "axis" }));
  g.append(svg("text", { x: pad, y: 12, class: "chart-label" }, label));
  g.append(svg("text", { x: pad, y: H - 4, class: "chart-label" }, fmtNum(edges[0], 1)));
  g.append(svg("text", { x: W - pad, y: H - 4, class: "chart-label", "text-anchor": "end" },
    fmtNum(edges[bins], 1)));
  return g;
}

function summaryLine(report) {
  const views = report.spaces.reduce((n, s) => n + s.counts.views, 0);
  const q = (name) => report.summary[name] && report.summary[name].n ?
    `${fmtNum(report.summary[name].q05, 1)}–${fmtNum(report.summary[name].q95, 1)}` : "–";
  return `${views} views, ${report.spaces.reduce((n, s) => n + s.counts.points, 0)} points, ` +
    `${report.spaces.reduce((n, s) => n + s.counts.cameras, 0)} cameras; fov ${q("fov_deg")}°, ` +
    `distance ${q("distance_m")} m (5–95%); planned in ${fmtNum(report.planning_s, 2)} s`;
}

// ------------------------------------------------------------------------------------------ page

function previewRow(p) {
  return h("div", { class: "design-preview", dataset: { point: p.point, view: p.view, fov: p.fov_deg } },
    h("div", { class: "muted" },
      `${p.space} · point ${p.point} · view ${p.view} · fov ${fmtNum(p.fov_deg, 1)}°`),
    h("div", { class: "tiles" }, DESIGN_CUES.filter((c) => p.images[c]).map((c) => h("div", { class: "tile" },
      h("img", { src: p.images[c], alt: c, width: 96, height: 96 }), h("span", {}, c)))));
}

async function viewDesigner(root) {
  const [schema, page] = await Promise.all([api("/designer/schema"), api("/spaces?limit=1000")]);
  const defaults = schemaDefaults(schema);
  const newSlot = (spec) => ({ spec: JSON.parse(JSON.stringify(spec)), report: null, seq: 0, sent: 0,
                               busy: false, pending: null, timer: null });
  const ds = { active: "a", slots: { a: newSlot(DESIGN_START), b: null }, target: null };
  const spaces = page.items;
  const replanAll = () => {
    ds.target = null;  // the capture fitted to belongs to the spaces picked then
    showFit();
    for (const n of ["a", "b"]) if (ds.slots[n]) schedule(n, { spec: ds.slots[n].spec });
  };
  const picks = h("div", { class: "cue-picks", id: "design-spaces" }, spaces.map((s, k) =>
    h("label", { class: "check" }, h("input", { type: "checkbox", class: "design-space", value: s.id,
                                                checked: k === 0, onchange: replanAll }),
      `${s.name} (#${s.id})`)));
  const spaceIds = () => [...picks.querySelectorAll("input:checked")].map((i) => Number(i.value));
  const error = h("p", { class: "error", id: "design-error", role: "alert" });
  const status = h("p", { class: "muted", id: "design-status", role: "status" });
  const yamlBox = h("textarea", { id: "design-yaml", rows: 18, spellcheck: "false",
    "aria-label": "the spec as YAML", oninput: () => schedule(ds.active, { spec_yaml: yamlBox.value }) });
  const onKnob = (path, value) => {
    const slot = ds.slots[ds.active];
    setPath(slot.spec, path, value);
    schedule(ds.active, { spec: slot.spec });
  };
  const form = h("form", { id: "design-form", onsubmit: (e) => e.preventDefault() },
    specForm(schema, onKnob));
  const hists = h("div", { id: "design-hists", class: "hists" });
  const cards = { a: slotCard("a"), b: slotCard("b") };
  cards.b.hidden = true;
  const tab = (n) => h("button", { type: "button", id: `slot-${n}`, class: "slot-tab",
                                   onclick: () => activate(n) }, `Spec ${n.toUpperCase()}`);
  const tabs = { a: tab("a"), b: tab("b") };
  tabs.b.hidden = true;
  const openB = (spec) => {
    ds.slots.b = Object.assign(ds.slots.b || newSlot(spec), { spec: JSON.parse(JSON.stringify(spec)) });
    cards.b.hidden = tabs.b.hidden = false;
    compare.hidden = true;
    activate("b");
    schedule("b", { spec: ds.slots.b.spec });
  };
  const compare = h("button", { type: "button", id: "design-compare", onclick: () => openB(ds.slots.a.spec) },
    "Compare: copy A to B");
  const fitButton = h("button", { type: "button", id: "design-fit", hidden: true, onclick: async () => {
    fitButton.disabled = true;
    status.textContent = "Fitting spec A to the capture (a few plans)…";
    try {
      const body = { space_ids: spaceIds(), spec: ds.slots.a.spec };
      const out = await api("/designer/fit", { method: "POST", body });
      ds.target = out.target;
      openB(out.spec);
      status.textContent = `B is A fitted to the ${out.source} capture (${out.frames} frames) in ` +
        `${fmtNum(out.fit_s, 1)} s; KS ` +
        Object.entries(out.ks).map(([k, v]) => `${k} ${fmtNum(v, 3)}`).join(", ");
    } catch (ex) { status.textContent = ""; error.textContent = `Fit: ${ex.message}`; }
    fitButton.disabled = false;
  } }, "Fit B to the capture");
  const showFit = () => {
    fitButton.hidden = !spaces.some((s) => spaceIds().includes(s.id) && s.frame && s.frame.capture);
  };
  const create = h("button", { type: "button", id: "design-create", onclick: async () => {
    const slot = ds.slots[ds.active];
    try {
      const job = await api("/jobs", { method: "POST", body: { space_ids: spaceIds(), spec: slot.spec } });
      status.replaceChildren(`Job #${job.id} created from spec ${ds.active.toUpperCase()}: `,
        h("a", { href: `#/jobs/${job.id}` }, "follow it"));
    } catch (ex) { error.textContent = `Create job: ${ex.message}`; }
  } }, "Create job");
  const download = h("button", { type: "button", id: "design-download", onclick: () => {
    const url = URL.createObjectURL(new Blob([yamlBox.value], { type: "application/yaml" }));
    const a = h("a", { href: url, download: `spec-${ds.active}.yaml` });
    document.body.append(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 1000);
  } }, "Download YAML");

  function slotCard(n) {
    return h("div", { class: "card slot-card", id: `design-slot-${n}`, dataset: { slot: n } },
      h("h2", {}, `Spec ${n.toUpperCase()}`), h("p", { class: "muted summary" }, "planning…"),
      h("div", { class: "plots" }), h("div", { class: "previews", id: `previews-${n}` }));
  }

  function activate(n) {
    ds.active = n;
    for (const k of ["a", "b"]) tabs[k].classList.toggle("active", k === n);
    const slot = ds.slots[n];
    fillForm(form, defaults, slot.spec);
    if (slot.report && document.activeElement !== yamlBox) yamlBox.value = slot.report.yaml;
  }

  function drawHists() {
    const a = ds.slots.a.report, b = ds.slots.b && ds.slots.b.report;
    if (!a) return;
    const t = ds.target;
    const series = (name) => [{ slot: "a", histogram: a.histograms[name] },
                              ...(b ? [{ slot: "b", histogram: b.histograms[name] }] : []),
                              ...(t && t[name] ? [{ slot: "t", histogram: t[name] }] : [])];
    hists.replaceChildren(...Object.keys(a.histograms).map((name) => overlayHistogram(name, series(name))));
  }

  function drawSlot(n) {
    const report = ds.slots[n].report, card = cards[n];
    card.querySelector(".summary").textContent = summaryLine(report);
    card.querySelector(".plots").replaceChildren(...report.spaces.flatMap((s) => [
      h("figure", { class: "plan" }, designPlot(s, [0, 1], n), designPlot(s, [0, 2], n),
        h("figcaption", {}, `${s.name}: top-down (x right, y up) and side (x right, z up), metres; ` +
          `${s.counts.cameras} cameras (squares), ${s.counts.points} points (dots)` +
          (s.shortfall ? `; ${s.shortfall}` : ""))),
    ]));
  }

  function schedule(n, body) {
    const slot = ds.slots[n];
    slot.pending = body;
    clearTimeout(slot.timer);
    slot.timer = setTimeout(() => pump(n), 200);
  }

  async function pump(n) {  // one request per slot at a time: the latest edit wins, none is lost
    const slot = ds.slots[n];
    if (!slot || slot.busy || !slot.pending) return;
    slot.busy = true;
    const body = slot.pending;
    slot.pending = null;
    try { await refresh(n, body); } finally { slot.busy = false; if (slot.pending) pump(n); }
  }

  async function refresh(n, body) {
    const slot = ds.slots[n], card = cards[n];
    const ids = spaceIds(), sent = ++slot.sent;
    if (!ids.length) { error.textContent = "Pick a space."; return; }
    card.classList.add("busy");
    let report;
    try {
      report = await api("/designer/plan", { method: "POST", body: { space_ids: ids, ...body } });
    } catch (ex) {
      card.classList.remove("busy");
      if (ex.status === 429) {  // other tabs hold this tenant's slots: ask again soon, unless edited since
        setTimeout(() => { if (slot.sent === sent && !slot.pending) schedule(n, body); }, 1000);
      }
      if (n === ds.active) error.textContent = `Spec ${n.toUpperCase()}: ${ex.message}`;
      return;
    }
    error.textContent = "";
    slot.spec = report.spec;
    slot.report = report;
    if (n === ds.active) activate(n);
    drawHists();
    drawSlot(n);
    card.dataset.planSeq = String(++slot.seq);
    if (slot.pending) { card.classList.remove("busy"); return; }  // a newer edit: its previews instead
    try {
      const body = { space_ids: ids, spec: report.spec };
      const out = await api("/designer/previews", { method: "POST", body });
      const box = card.querySelector(".previews");
      box.replaceChildren(...out.previews.map(previewRow),
        h("p", { class: "muted" }, `rendered in ${fmtNum(out.render_s, 2)} s`));
      box.dataset.spec = JSON.stringify(report.spec);
    } catch (ex) { if (n === ds.active) error.textContent = `Previews: ${ex.message}`; }
    card.classList.remove("busy");
  }

  root.append(h("section", { id: "designer" },
    h("div", { class: "row" }, h("h1", {}, "Designer"),
      h("span", { class: "muted" }, "a spec's cameras, points, distributions and previews before any job")),
    h("div", { class: "card" }, h("h2", {}, "Spaces"),
      spaces.length ? picks : h("p", { class: "muted" }, "Upload a space first (Jobs page).")),
    h("div", { class: "design-top" },
      h("div", { class: "card design-edit" },
        h("div", { class: "row" }, tabs.a, tabs.b, compare, fitButton, h("span", { class: "spacer" }),
          create, download),
        error, status,
        h("div", { class: "design-spec" }, h("div", { class: "design-form-box" }, form),
          h("label", { class: "design-yaml-box" }, "YAML (edit either side)", yamlBox))),
      h("div", { class: "card" },
        h("h2", {}, "Distributions: A filled, B outlined, capture dashed"),
        hists)),
    h("div", { class: "two" }, cards.a, cards.b)));
  activate("a");
  showFit();
  if (spaces.length) schedule("a", { spec: ds.slots.a.spec });
}
