// The playground page: a form built from the spec's JSON schema (targets and asset lists by classes.js), validated
// by the server's model, a debounced preview with its boxes by class (the latest request wins), a strip of neighbouring frames, YAML download, generate, and water from a photo.
"use strict";

const $ = (id) => document.getElementById(id);
const client = (crypto.randomUUID ? crypto.randomUUID() : String(Math.random())).slice(0, 36);
let config = null, spec = {}, defs = {}, timer = null, frameTimer = null, inflight = null, stripInflight = null;
let lastYaml = "", calibWater = null, validated = 0;
let shownDefaults = {};  // a section's default as the form shows it, by path: an edit inside a missing section starts there

// ---- JSON with integers beyond 2^53 (seeds go to 2^63 - 1) kept exact, as BigInt
function parseJSON(text) {
  return JSON.parse(text, (k, v, ctx) =>
    (typeof v === "number" && Number.isInteger(v) && !Number.isSafeInteger(v) && ctx && /^-?\d+$/.test(ctx.source))
      ? BigInt(ctx.source) : v);
}
function toJSON(value) {
  return JSON.stringify(value, (k, v) => (typeof v === "bigint" ? `__bigint__${v}` : v))
    .replace(/"__bigint__(-?\d+)"/g, "$1");
}

// ---- HTTP: the API key (kept for this tab only), JSON, 401 asks for a key, 503 says the server is busy.
// Paths are relative ("playground/preview"): the page is at <root>/playground, so they resolve against the API's
// root wherever a proxy mounts it (https://host/seasynth/playground calls https://host/seasynth/playground/preview).
function headers(extra) {
  const h = Object.assign({"X-Playground-Client": client}, extra || {});
  const key = sessionStorage.getItem("seasynth-key");
  if (key) h["X-API-Key"] = key;
  return h;
}
async function call(method, path, body, signal, extraHeaders) {
  const kind = body instanceof FormData ? {} : {"Content-Type": "application/json"};
  const opts = {method, headers: headers(Object.assign(kind, extraHeaders || {})), signal};
  if (body !== undefined) opts.body = body instanceof FormData ? body : toJSON(body);
  const r = await fetch(path, opts);
  if (r.status === 401) { $("key-box").hidden = false; status("an API key is required"); }
  const data = r.headers.get("content-type")?.includes("json") ? parseJSON(await r.text()) : null;
  return {status: r.status, data, retry: Number(r.headers.get("Retry-After") || 1)};
}
function status(text) { $("status").textContent = text; }

// ---- spec values by path
function getAt(obj, path) { return path.reduce((o, k) => (o == null ? undefined : o[k]), obj); }
function setAt(obj, path, value) {
  let o = obj;
  path.slice(0, -1).forEach((k, n) => {  // a missing section starts as the form showed it, so one edit keeps the rest
    if (o[k] == null || typeof o[k] !== "object") {
      const shown = shownDefaults[pid(path.slice(0, n + 1))];
      o[k] = shown && typeof shown === "object" ? structuredClone(shown) : {};
    }
    o = o[k];
  });
  if (value === undefined) delete o[path[path.length - 1]]; else o[path[path.length - 1]] = value;
  // A section left empty goes, so an optional one (terrain.mesh, ...) is unset again rather than set to {}.
  for (let n = path.length - 1; n > 0 && value === undefined; n--) {
    const parent = getAt(obj, path.slice(0, n));
    if (parent && typeof parent === "object" && !Array.isArray(parent) && Object.keys(parent).length === 0) {
      delete getAt(obj, path.slice(0, n - 1))[path[n - 1]];
    } else break;
  }
}
const pid = (path) => path.join(".");
function resolve(s) {
  while (s && s.$ref) s = defs[s.$ref.split("/").pop()];
  if (s && s.anyOf) {
    const real = s.anyOf.filter((x) => x.type !== "null");
    if (real.length === 1) return Object.assign({}, resolve(real[0]), {nullable: true, default: s.default});
  }
  return s || {};
}

// ---- the form
function buildForm() {
  defs = config.schema.$defs || {};
  shownDefaults = {};
  const form = $("spec-form");
  form.innerHTML = "";
  for (const [name, sub] of Object.entries(config.schema.properties)) addField(form, [name], sub);
}
function label(path) { return String(path[path.length - 1]).replace(/_/g, " "); }
function addField(parent, path, raw, inherited) {
  // A field's default is its own, or its part of the enclosing section's default (e.g. workspaces.camera.min).
  const s = resolve(raw), own = raw.default !== undefined ? raw.default : s.default;
  const dflt = own !== undefined ? own : inherited;
  const current = getAt(spec, path), value = current !== undefined ? current : dflt;
  if (pid(path) === "targets") { parent.appendChild(classesEditor(path, value)); return; }  // classes.js
  if (s.type === "object" && s.properties) {
    if (dflt && typeof dflt === "object") shownDefaults[pid(path)] = dflt;
    const fs = document.createElement("fieldset");
    fs.innerHTML = `<legend>${label(path)}</legend>`;
    fs.id = "f-" + pid(path);
    for (const [k, sub] of Object.entries(s.properties)) addField(fs, path.concat(k), sub, dflt ? dflt[k] : undefined);
    fs.appendChild(errorSpan(path));
    parent.appendChild(fs);
    return;
  }
  const row = document.createElement("div");
  row.className = "field";
  row.innerHTML = `<span title="${(s.description || "").replace(/"/g, "'")}">${label(path)}</span>`;
  row.appendChild(control(path, s, value));
  row.appendChild(errorSpan(path));
  parent.appendChild(row);
}
function errorSpan(path) {
  const e = document.createElement("span");
  e.className = "field-error"; e.id = "e-" + pid(path);
  return e;
}
function numberValue(text, integer) {
  if (text === "") return undefined;
  if (integer && /^-?\d+$/.test(text) && !Number.isSafeInteger(Number(text))) return BigInt(text);  // exact
  return Number(text);
}
function numberInput(id, value, onValue, integer) {
  const i = document.createElement("input");
  i.type = "number"; i.step = integer ? "1" : "any"; i.id = "f-" + id;
  if (value != null) i.value = String(value);
  i.addEventListener("input", () => onValue(numberValue(i.value, integer)));
  return i;
}
function control(path, s, value) {
  if (pid(path) === "water.jerlov") return jerlovControl(path, value || []);
  if (pid(path) === "distractors.assets") return assetPicker(path, value, (v) => changed(path, v));
  if (s.enum) {
    const sel = document.createElement("select");
    sel.id = "f-" + pid(path);
    if (s.nullable) sel.add(new Option("(unset)", ""));
    for (const v of s.enum) sel.add(new Option(v, v));
    sel.value = value == null ? "" : value;
    sel.addEventListener("change", () => changed(path, sel.value === "" ? undefined : sel.value));
    return sel;
  }
  if (s.type === "boolean") {
    const c = document.createElement("input");
    c.type = "checkbox"; c.id = "f-" + pid(path); c.checked = !!value;
    c.addEventListener("change", () => changed(path, c.checked));
    return c;
  }
  if (s.type === "number" || s.type === "integer") {
    return numberInput(pid(path), value, (v) => changed(path, v), s.type === "integer");
  }
  if (s.type === "array" && s.prefixItems && s.prefixItems.every((x) => ["number", "integer"].includes(resolve(x).type))) {
    const pair = document.createElement("span");
    pair.className = "pair"; pair.id = "f-" + pid(path);
    const n = s.prefixItems.length, vals = Array.isArray(value) ? value.slice() : new Array(n).fill(null);
    s.prefixItems.forEach((item, k) => {
      const i = numberInput(pid(path.concat(k)), vals[k], (v) => {
        vals[k] = v === undefined ? null : v;
        changed(path, vals.every((x) => x == null) ? undefined : vals.slice());  // all cleared: unset again
      }, resolve(item).type === "integer");
      i.placeholder = n === 2 ? ["min", "max"][k] : "xyz"[k] || String(k);
      pair.appendChild(i);
    });
    return pair;
  }
  if (s.type === "string") {
    const t = document.createElement("input");
    t.id = "f-" + pid(path); t.value = value == null ? "" : value;
    t.addEventListener("input", () => changed(path, t.value === "" ? undefined : t.value));
    return t;
  }
  // Anything else (lists of assets or lamps, intrinsics, ...) is edited as JSON.
  const ta = document.createElement("textarea");
  ta.id = "f-" + pid(path); ta.rows = 3; ta.value = value === undefined ? "" : toJSON(value);
  ta.addEventListener("input", () => {
    try { changed(path, ta.value.trim() === "" ? undefined : parseJSON(ta.value)); ta.classList.remove("invalid"); }
    catch (err) { ta.classList.add("invalid"); $("e-" + pid(path)).textContent = "not JSON: " + err.message; }
  });
  return ta;
}
function jerlovControl(path, chosen) {
  const box = document.createElement("span");
  box.className = "jerlov"; box.id = "f-" + pid(path);
  for (const [name, rgb] of Object.entries(config.jerlov)) {
    const l = document.createElement("label"), c = document.createElement("input");
    c.type = "checkbox"; c.value = name; c.id = "f-water.jerlov-" + name; c.checked = chosen.includes(name);
    const srgb = rgb.map((v) => Math.round(255 * (v <= 0.0031308 ? 12.92 * v : 1.055 * v ** (1 / 2.4) - 0.055)));
    l.appendChild(c);
    l.insertAdjacentHTML("beforeend", `<span class="swatch" style="background:rgb(${srgb})"></span> ${name}`);
    c.addEventListener("change", () => {  // repeats weight the draw: types still chosen keep theirs
      const now = getAt(spec, path) || chosen;
      changed(path, c.checked ? now.concat([name]) : now.filter((x) => x !== name));
    });
    box.appendChild(l);
  }
  return box;
}

// ---- validate, then preview (debounced; a newer change aborts the request in flight)
function changed(path, value) {
  setAt(spec, path, value);
  clearTimeout(timer);
  timer = setTimeout(refresh, 250);
}
function showErrors(errors) {
  document.querySelectorAll(".field-error").forEach((e) => (e.textContent = ""));
  document.querySelectorAll(".invalid").forEach((e) => e.classList.remove("invalid"));
  const loose = [];
  for (const err of errors) {
    // a placement's error names its kind after "placement" (pydantic's tag of the union): its fields sit without it
    let loc = err.loc.filter((k, n) => !(err.loc[n - 1] === "placement" && typeof k === "string" && n < err.loc.length - 1)),
      span = null;
    while (loc.length && !(span = $("e-" + pid(loc)))) loc.pop();
    if (!span) { loose.push(`${err.loc.join(".")}: ${err.msg}`); continue; }
    span.textContent = (span.textContent ? span.textContent + "; " : "") + err.msg;
    $("f-" + pid(loc))?.classList.add("invalid");
  }
  $("errors").textContent = loose.join("\n");
}
function views() { return [...document.querySelectorAll("[data-view]:checked")].map((c) => c.dataset.view); }
async function refresh() {
  clearTimeout(frameTimer);  // its preview comes with this one's
  const mine = ++validated;
  const v = await call("POST", "playground/validate", {spec});
  if (mine !== validated) return;  // a newer spec was sent meanwhile: its answer decides
  if (v.status !== 200) return;
  showErrors(v.data.errors);
  if (!v.data.valid) { status("the spec has errors"); return; }
  lastYaml = v.data.yaml;
  $("spec-yaml").value = lastYaml;
  preview();
  strip();
}
async function preview() {
  if (inflight) inflight.abort();
  const ctl = inflight = new AbortController();
  status("rendering…");
  try {
    const r = await call("POST", "playground/preview", {spec, frame: Number($("frame").value) || 0, views: views()}, ctl.signal);
    if (r.status === 503) { status("the renderer is busy; retrying"); setTimeout(preview, 1000 * r.retry); return; }
    if (r.status === 409) return;  // a newer request of ours replaced it
    if (r.status !== 200) { status(r.data ? r.data.detail : `error ${r.status}`); return; }
    show(r.data);
    status(`frame ${r.data.frame} rendered`);
  } catch (err) { if (err.name !== "AbortError") status(String(err)); }
  finally { if (inflight === ctl) inflight = null; }
}
function show(p) {
  const img = $("preview-image");
  img.onload = () => drawBoxes(p);
  img.src = p.images.image;
  img.dataset.frame = p.frame;
  $("render-ms").textContent = `${p.render_ms} ms`;
  const extra = $("extra-views");
  extra.innerHTML = "";
  for (const name of ["depth", "instance", "clean", "air"]) {
    if (!p.images[name]) continue;
    const i = document.createElement("img");
    i.src = p.images[name]; i.id = "view-image-" + name; i.title = name;
    extra.appendChild(i);
  }
}
function drawBoxes(p) {
  const img = $("preview-image"), c = $("preview-boxes"), k = img.clientWidth / p.width;
  c.width = img.clientWidth; c.height = img.clientHeight;
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  c.dataset.boxes = p.boxes.length;
  drawLegend(p.boxes);
  if (!$("show-boxes").checked) return;
  g.lineWidth = 2; g.font = "13px sans-serif";
  for (const b of p.boxes) {  // KITTI boxes hold inclusive pixel indices: the outline runs round those pixels
    const [l, t, r, btm] = b.box;
    g.strokeStyle = g.fillStyle = boxColour(b.class);
    g.strokeRect(l * k, t * k, (r - l + 1) * k, (btm - t + 1) * k);
    g.fillText(b.class, l * k + 2, Math.max(12, t * k - 3));
  }
}
async function strip() {
  if (stripInflight) stripInflight.abort();
  const ctl = stripInflight = new AbortController();
  const frames = spec.frames || config.schema.properties.frames.default;
  const first = Math.max(0, Math.min((Number($("frame").value) || 0) - 3, frames - 8));
  try {
    const r = await call("POST", "playground/strip", {spec, first, count: 8}, ctl.signal);
    if (r.status === 503) { setTimeout(() => { if (stripInflight === null) strip(); }, 1000 * r.retry); return; }
    if (r.status === 409) return;  // a newer strip of ours replaced it
    if (r.status !== 200) { status("strip: " + (r.data ? r.data.detail : `error ${r.status}`)); return; }
    const box = $("strip");
    box.innerHTML = "";
    for (const f of r.data.frames) {
      const i = document.createElement("img");
      i.src = f.image; i.title = `frame ${f.frame}`; i.dataset.frame = f.frame;
      i.addEventListener("click", () => { $("frame").value = f.frame; preview(); });
      box.appendChild(i);
    }
  } catch (err) { if (err.name !== "AbortError") status(String(err)); }
  finally { if (stripInflight === ctl) stripInflight = null; }
}

// ---- YAML and generate
function downloadYaml() {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(new Blob([lastYaml], {type: "application/yaml"}));
  a.download = "spec.yaml";
  a.click();
}
async function generate() {
  const path = config.mode === "service" ? "datasets" : "playground/generate";
  const r = await call("POST", path, spec);
  if (r.status !== 201 && r.status !== 202 && r.status !== 200) {
    $("generate-progress").textContent = r.data ? r.data.detail : `error ${r.status}`; return;
  }
  const id = r.data.id;
  const poll = async () => {
    const s = await call("GET", `${path}/${id}`);
    if (s.status !== 200) { $("generate-progress").textContent = `error ${s.status}`; return; }
    const d = s.data;
    $("generate-progress").textContent = `${id.slice(0, 8)}: ${d.state}, ${d.frames_done}/${d.frames_total} frames` +
      (d.out ? ` in ${d.out}` : "") + (d.error ? ` (${d.error})` : "");
    if (!["succeeded", "failed", "cancelled"].includes(d.state)) setTimeout(poll, 1000);
  };
  poll();
}

// ---- water from a photo
function stats(img) {
  const c = document.createElement("canvas");
  c.width = img.naturalWidth; c.height = img.naturalHeight;
  const g = c.getContext("2d");
  g.drawImage(img, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data, n = d.length / 4, sum = [0, 0, 0], sq = [0, 0, 0];
  for (let i = 0; i < d.length; i += 4) for (let k = 0; k < 3; k++) { sum[k] += d[i + k]; sq[k] += d[i + k] ** 2; }
  return sum.map((s, k) => [s / n, Math.sqrt(Math.max(0, sq[k] / n - (s / n) ** 2))]);
}
function showStats() {
  const a = $("calib-photo-view"), b = $("calib-frame");
  if (!a.complete || !b.complete || !a.naturalWidth || !b.naturalWidth) return;
  const sa = stats(a), sb = stats(b), rows = ["R", "G", "B"].map((ch, k) =>
    `<tr><th>${ch}</th><td>${sa[k][0].toFixed(1)}</td><td>${sa[k][1].toFixed(1)}</td>` +
    `<td>${sb[k][0].toFixed(1)}</td><td>${sb[k][1].toFixed(1)}</td></tr>`);
  $("calib-stats").innerHTML = "<tr><th></th><th>photo mean</th><th>sd</th><th>seasynth mean</th><th>sd</th></tr>" + rows.join("");
}
async function calibrate() {
  const photo = $("calib-photo").files[0];
  if (!photo) { $("calib-result").textContent = "choose a photo first"; return; }
  const form = new FormData();
  form.append("photo", photo);
  if ($("calib-depth").files[0]) form.append("depth", $("calib-depth").files[0]);
  $("calib-result").textContent = "estimating…";
  const prior = $("calib-prior").value;  // "" : the default prior
  const r = await call("POST", prior ? `calibrate?prior=${encodeURIComponent(prior)}` : "calibrate", form);
  if (r.status !== 200) { $("calib-result").textContent = r.data ? r.data.detail : `error ${r.status}`; return; }
  calibWater = r.data.water;
  $("calib-result").innerHTML = calibrationTable(r.data);
  $("calib-apply").disabled = false;
  $("calib-photo-view").onload = showStats;
  $("calib-photo-view").src = URL.createObjectURL(photo);
  const trial = structuredClone(spec);
  trial.water = calibWater;
  // Its own client name: the page's preview and this one do not replace each other.
  const p = await call("POST", "playground/preview", {spec: trial, frame: Number($("frame").value) || 0, views: []},
                       undefined, {"X-Playground-Client": client + ":calibration"});
  if (p.status === 200) { $("calib-frame").onload = showStats; $("calib-frame").src = p.data.images.image; }
}
function calibrationTable(c) {
  // Per coefficient (R, G, B): a value with its 1-sigma, or "not identified" in a channel the photo cannot tell.
  const e = c.estimate, cell = (v, sd, k) => (v == null || v[k] == null ? "not identified"
    : `${v[k].toFixed(3)}${sd && sd[k] != null ? " ± " + sd[k].toFixed(3) : ""}`);
  const rows = ["beta_D", "beta_B", "B_inf", "beta_D_ratio", "beta_B_ratio"].filter((k) => k in e).map((k) =>
    `<tr><th>${k}</th>` + [0, 1, 2].map((ch) => `<td id="calib-${k}-${"RGB"[ch]}">${cell(e[k], e[k + "_sd"], ch)}</td>`).join("") + "</tr>");
  return `<table><tr><th></th><th>R</th><th>G</th><th>B</th></tr>${rows.join("")}</table>` +
    `<p>nearest Jerlov type: <b id="calib-jerlov">${e.nearest_jerlov || "none"}</b> · ${e.with_range ? "with" : "without"} range</p>` +
    `<p id="calib-notes">${(e.notes || []).join("<br>")}</p>`;
}
function applyCalibration() {
  spec.water = calibWater;
  buildForm();
  refresh();
}

// ---- start
async function start() {
  const r = await call("GET", "playground/config");
  if (r.status !== 200) return;
  config = r.data;
  spec = structuredClone(config.spec);
  $("mode").textContent = `${config.mode} · ${config.version}`;
  if (config.mode === "service") await loadUploads();  // classes.js: the pickers list them
  buildForm();
  refresh();
}
// A frame change previews on its own timer: a spec edit waiting to be validated is not dropped (refresh previews too).
$("frame").addEventListener("input", () => {
  clearTimeout(frameTimer);
  frameTimer = setTimeout(() => { preview(); strip(); }, 250);
});
const savedKey = sessionStorage.getItem("seasynth-key");
if (savedKey) $("api-key").value = savedKey;
$("api-key").addEventListener("change", () => { sessionStorage.setItem("seasynth-key", $("api-key").value); start(); });
document.querySelectorAll("[data-view]").forEach((c) => c.addEventListener("change", preview));
$("show-boxes").addEventListener("change", preview);
$("download-yaml").addEventListener("click", downloadYaml);
$("generate").addEventListener("click", generate);
$("calib-run").addEventListener("click", calibrate);
$("calib-apply").addEventListener("click", applyCalibration);
start();
