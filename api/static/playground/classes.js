// The playground's class editor and asset picker: `targets` as a list of classes (add, remove, reorder; a name,
// a placement, counts, scales and assets each), and a picker of procedural kinds by thumbnail, which the
// distractors' assets use too. Loaded before app.js, whose helpers (changed, numberInput, errorSpan, ...) it calls.
"use strict";

// Class i's colour, in the editor and on the preview's boxes and legend.
const CLASS_COLOURS = ["#ffea00", "#00e5ff", "#ff4081", "#76ff03", "#ff9100", "#d500f9", "#ffffff", "#2979ff"];
const classColour = (i) => (i < 0 ? "#9e9e9e" : CLASS_COLOURS[i % CLASS_COLOURS.length]);
// Each placement's model and its ranges (min, max); water's schools have their own fields (schoolFields).
const PLACEMENT_RANGES = {buried: ["Buried", ["sunk_fraction"]],
                          water: ["InWater", ["height_m", "yaw_deg", "pitch_deg", "roll_deg"]]};

function targetsOf(value) {  // one mapping is a list of that one class
  if (Array.isArray(value)) return value;
  return [value && typeof value === "object" ? value : {}];
}
function classNames() { return targetsOf(spec.targets).map((c) => c.class_name ?? defs.Targets.properties.class_name.default); }

// ---- a pair of number fields (min, max); the shown default is written with the edited half
function pairControl(path, shown, integer, onPair) {
  const pair = document.createElement("span"), vals = (shown || [null, null]).slice();
  pair.className = "pair"; pair.id = "f-" + pid(path);
  ["min", "max"].forEach((name, k) => {
    const i = numberInput(pid(path.concat(k)), vals[k], (v) => {
      vals[k] = v === undefined ? null : v;
      onPair(vals.every((x) => x == null) ? undefined : vals.slice());
    }, integer);
    i.placeholder = name;
    pair.appendChild(i);
  });
  return pair;
}
function row(parent, path, title, controlEl) {
  const r = document.createElement("div");
  r.className = "field";
  r.innerHTML = `<span>${title}</span>`;
  r.appendChild(controlEl);
  r.appendChild(errorSpan(path));
  parent.appendChild(r);
}

// ---- the asset picker: a thumbnail per procedural kind (ticked: in the list, with its variants), one per mesh
// uploaded to the service (GET assets lists them; their pictures are drawn there), and the list's other assets
// (local paths, asset ids) by name, removable, with a field to add one.
const uploads = [];  // {asset_id, filename, thumbnail} of the service's uploaded meshes, newest first
const pictures = new Map();  // asset_id -> a promise of the picture's object URL (null: none), fetched once
const MAX_LISTED = 1000;  // uploads shown (the list's pages of 100)

async function loadUploads() {
  const got = new Map();
  for (let url = "assets?limit=100"; url && got.size < MAX_LISTED;) {
    const r = await call("GET", url);
    if (r.status !== 200 || !r.data) break;  // (the page works on without them)
    for (const a of r.data.items) if (a.kind === "mesh") got.set(a.asset_id, a);  // (an upload between pages: once)
    url = r.data.next && r.data.next.replace(/^\//, "");  // relative, as every call of the page
  }
  uploads.splice(0, uploads.length, ...got.values());  // at once: a second load (the key given) replaces the first
}
// The picture comes with the API key (an <img> would send none): fetched, then shown from a blob.
function uploadPicture(u) {
  if (!pictures.has(u.asset_id)) {
    pictures.set(u.asset_id, !u.thumbnail ? Promise.resolve(null) : fetch(u.thumbnail.replace(/^\//, ""), {headers: headers()})
      .then((r) => (r.ok ? r.blob().then((b) => URL.createObjectURL(b)) : null)).catch(() => null));
  }
  const img = document.createElement("img");
  img.alt = u.filename; img.className = "upload-picture"; img.dataset.state = "loading";
  pictures.get(u.asset_id).then((src) => {
    if (src) { img.src = src; img.dataset.state = "shown"; return; }
    const icon = document.createElement("span");  // a mesh with no picture still lists, by name
    icon.className = "upload-picture mesh-icon"; icon.dataset.state = "none"; icon.textContent = "no picture";
    img.replaceWith(icon);
  });
  return img;
}

function pickTile(path, list, key, title, picture, same, entry, emit, withVariants) {
  const tile = document.createElement("label"), tick = document.createElement("input"), name = document.createElement("span");
  tile.className = "kind"; tile.id = `pick-${pid(path)}-${key}`; tile.title = title;
  tick.type = "checkbox"; tick.checked = list.some(same);
  name.textContent = title;
  tile.append(tick, picture, name);
  let variants = null;
  if (withVariants) {  // (variants are a procedural kind's; a mesh is itself)
    variants = numberInput(`${pid(path)}-${key}-variants`, list.find(same)?.variants, (v) => {
      const a = list.find(same);
      if (!a) return;
      if (v === undefined) delete a.variants; else a.variants = v;
      emit();
    }, true);
    variants.placeholder = `${resolve(defs.AssetRef.properties.variants).default} variants`; variants.title = "variants";
    tile.appendChild(variants);
  }
  const show = () => { tile.classList.toggle("picked", tick.checked); if (variants) variants.hidden = !tick.checked; };
  show();
  tick.addEventListener("change", () => {
    const at = list.findIndex(same);
    if (tick.checked && at < 0) list.push(entry());
    if (!tick.checked && at >= 0) list.splice(at, 1);
    show(); emit();
  });
  return tile;
}
function assetPicker(path, assets, onAssets) {
  const box = document.createElement("div");
  box.className = "picker"; box.id = "f-" + pid(path);
  const list = (assets || []).map((a) => Object.assign({}, a));
  const emit = () => onAssets(list.map((a) => Object.assign({}, a)));
  for (const kind of config.kinds) {
    const img = document.createElement("img");
    img.src = `playground/kinds/${kind}.png`; img.alt = kind; img.loading = "lazy";
    box.appendChild(pickTile(path, list, kind, kind, img, (a) => a.procedural === kind, () => ({procedural: kind}),
                             emit, true));
  }
  for (const u of uploads) {
    box.appendChild(pickTile(path, list, "upload-" + u.asset_id.slice(0, 12), u.filename, uploadPicture(u),
                             (a) => a.asset_id === u.asset_id, () => ({asset_id: u.asset_id}), emit, false));
  }
  const others = document.createElement("div");
  others.className = "other-assets";
  const drawOthers = () => {
    others.innerHTML = "";
    list.forEach((a, n) => {
      if (a.procedural != null || uploads.some((u) => u.asset_id === a.asset_id)) return;  // a tile shows it
      const chip = document.createElement("span"), x = document.createElement("button");
      chip.className = "chip"; chip.textContent = a.path != null ? a.path : `asset ${a.asset_id}`;
      x.type = "button"; x.textContent = "×"; x.title = "remove";
      x.addEventListener("click", () => { list.splice(n, 1); drawOthers(); emit(); });
      chip.appendChild(x);
      others.appendChild(chip);
    });
    const add = document.createElement("input"), go = document.createElement("button");
    add.placeholder = "mesh path or uploaded asset id"; add.id = `f-${pid(path)}-other`;
    go.type = "button"; go.textContent = "add";
    go.addEventListener("click", () => {
      const t = add.value.trim();
      if (!t) return;
      list.push(/^[0-9a-f]{16,}$/i.test(t) ? {asset_id: t} : {path: t});  // an upload's id is hex
      drawOthers(); emit();
    });
    others.append(add, go);
    if (config.mode === "service") others.appendChild(uploadControl(path, list, emit));
  };
  drawOthers();
  box.appendChild(others);
  return box;
}
// Upload a mesh to the service (POST /assets) and tick it here; every picker then shows it.
function uploadControl(path, list, emit) {
  const l = document.createElement("label"), file = document.createElement("input"), said = document.createElement("span");
  file.type = "file"; file.id = `upload-${pid(path)}`; file.accept = ".glb,.gltf,.obj,.ply,.stl,.zip";
  said.className = "upload-error";
  l.append("upload a mesh ", file, said);
  file.addEventListener("change", async () => {
    if (!file.files[0]) return;
    const form = new FormData();
    form.append("file", file.files[0]);
    said.textContent = "uploading…";
    const r = await call("POST", "assets", form);
    if (r.status !== 200 && r.status !== 201) { said.textContent = r.data ? r.data.detail : `error ${r.status}`; return; }
    const {asset_id, filename} = r.data;
    if (!uploads.some((u) => u.asset_id === asset_id)) {
      uploads.unshift({asset_id, filename, thumbnail: `assets/${asset_id}/thumbnail.png`});
    }
    if (!list.some((a) => a.asset_id === asset_id)) list.push({asset_id});
    emit();
    buildForm();  // every picker shows the new mesh
  });
  return l;
}

// ---- the classes
function classesEditor(path, value) {
  const fs = document.createElement("fieldset");
  fs.id = "f-" + pid(path);
  const draw = () => {
    const classes = targetsOf(getAt(spec, path) ?? value).map((c) => structuredClone(c));
    const emit = () => changed(path, classes.map((c) => structuredClone(c)));
    fs.innerHTML = "<legend>targets: classes</legend>";
    classes.forEach((c, i) => fs.appendChild(classCard(path.concat(i), c, i, classes, emit, draw)));
    const add = document.createElement("button");
    add.type = "button"; add.id = "add-class"; add.textContent = "add a class";
    add.addEventListener("click", () => {
      const taken = new Set(classes.map((x) => x.class_name));
      let n = classes.length + 1;
      while (taken.has(`Class${n}`)) n++;
      classes.push({class_name: `Class${n}`, assets: []});
      emit(); draw();
    });
    fs.appendChild(add);
    fs.appendChild(errorSpan(path));
  };
  draw();
  return fs;
}
function classCard(path, c, i, classes, emit, redraw) {
  const T = defs.Targets.properties, card = document.createElement("fieldset");
  card.className = "class-card"; card.id = "f-" + pid(path);
  card.style.borderLeftColor = classColour(i);
  card.innerHTML = `<legend><span class="swatch" style="background:${classColour(i)}"></span> class ${i}</legend>`;
  const tools = document.createElement("span");
  tools.className = "class-tools";
  for (const [name, text, ok, act] of [
    ["up", "↑", i > 0, () => classes.splice(i - 1, 0, classes.splice(i, 1)[0])],
    ["down", "↓", i < classes.length - 1, () => classes.splice(i + 1, 0, classes.splice(i, 1)[0])],
    ["remove", "remove", classes.length > 1, () => classes.splice(i, 1)]]) {
    const b = document.createElement("button");
    b.type = "button"; b.id = `class-${name}-${i}`; b.textContent = text; b.disabled = !ok;
    b.addEventListener("click", () => { act(); emit(); redraw(); });
    tools.appendChild(b);
  }
  card.appendChild(tools);
  const name = document.createElement("input");
  name.id = "f-" + pid(path.concat("class_name")); name.value = c.class_name ?? T.class_name.default;
  name.addEventListener("input", () => { c.class_name = name.value; emit(); });
  row(card, path.concat("class_name"), "name", name);
  // placement: its kind, and the ranges that kind takes (an edit writes the one field; the rest stay as written)
  const p = typeof c.placement === "string" ? {kind: c.placement} : (c.placement || {kind: "seabed"});
  const kind = document.createElement("select");
  kind.id = "f-" + pid(path.concat("placement", "kind"));
  for (const k of ["seabed", "buried", "water"]) kind.add(new Option(k, k));
  kind.value = p.kind;
  kind.addEventListener("change", () => { c.placement = {kind: kind.value}; emit(); redraw(); });
  row(card, path.concat("placement"), "placement", kind);
  const editPlacement = (edit) => {
    // (`placement: water` may be written by its kind alone: the shown mapping takes the edit)
    c.placement = Object.assign({}, c.placement && typeof c.placement === "object" ? c.placement : p);
    edit(c.placement);
    emit();
  };
  const put = (o, field, v) => { if (v === undefined) delete o[field]; else o[field] = v; };
  const [model, ranges] = PLACEMENT_RANGES[p.kind] || [null, []];
  for (const field of ranges) {
    row(card, path.concat("placement", field), field.replace(/_/g, " "),
        pairControl(path.concat("placement", field), p[field] ?? defs[model].properties[field].default, false,
                    (v) => editPlacement((pl) => put(pl, field, v))));
  }
  if (p.kind === "water") schoolFields(card, path.concat("placement", "school"), p.school, editPlacement, put, redraw);
  for (const [field, integer] of [["count", true], ["scale", false]]) {
    row(card, path.concat(field), field, pairControl(path.concat(field), c[field] ?? T[field].default, integer,
      (v) => { put(c, field, v); emit(); }));
  }
  const assets = c.assets ?? [{procedural: "urchin"}];
  row(card, path.concat("assets"), "assets", assetPicker(path.concat("assets"), assets, (list) => {
    c.assets = list; emit();
  }));
  return card;
}

// Water's schools: a tick (count then counts schools), and each school's size, spacing and heading jitter.
function schoolFields(card, path, school, editPlacement, put, redraw) {
  const S = defs.School.properties, on = document.createElement("input");
  on.type = "checkbox"; on.id = "f-" + pid(path); on.checked = school != null;
  on.addEventListener("change", () => {
    editPlacement((pl) => { if (on.checked) pl.school = {}; else delete pl.school; });
    redraw();
  });
  row(card, path, "in schools", on);
  if (school == null) return;
  const edit = (field, v) => editPlacement((pl) => { pl.school = Object.assign({}, pl.school); put(pl.school, field, v); });
  for (const [field, integer] of [["size", true], ["spacing_m", false]]) {
    row(card, path.concat(field), `school ${field.replace(/_/g, " ")}`,
        pairControl(path.concat(field), school[field] ?? S[field].default, integer, (v) => edit(field, v)));
  }
  const jitter = numberInput(pid(path.concat("heading_jitter_deg")), school.heading_jitter_deg ?? S.heading_jitter_deg.default,
                             (v) => edit("heading_jitter_deg", v), false);
  row(card, path.concat("heading_jitter_deg"), "heading jitter deg", jitter);
}

// ---- the preview's legend: each class of the frame's boxes, in its colour, with its count
function boxColour(name) { return classColour(classNames().indexOf(name)); }
function drawLegend(boxes) {
  const legend = $("legend"), names = classNames(), counts = {};
  for (const b of boxes) counts[b.class] = (counts[b.class] || 0) + 1;
  const order = names.concat(Object.keys(counts).filter((n) => !names.includes(n)));  // DontCare last
  legend.innerHTML = "";
  for (const n of order) {
    const item = document.createElement("span");
    item.className = "legend-item"; item.dataset.class = n; item.dataset.count = counts[n] || 0;
    item.innerHTML = `<span class="swatch" style="background:${boxColour(n)}"></span> ${n} ${counts[n] || 0}`;
    legend.appendChild(item);
  }
}
