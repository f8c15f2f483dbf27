// Workbench marked-point picker. Pixel convention (docs/conventions.md): pixel (0, 0) is the centre of the
// top-left pixel, so image pixel i covers [i - 0.5, i + 0.5]; on screen: x = (u + 0.5) * scale + ox.
"use strict";
const S = { doc: null, photo: null, car: null, point: null, manual: [], rejected: [], undo: [], img: null,
            scale: 1, ox: 0, oy: 0, faceImgs: {}, dirty: false };
const $ = (id) => document.getElementById(id);
// the run's token (the server puts it in the page): sent with every API request; without it the server refuses
const TOKEN = document.querySelector('meta[name="picker-token"]').content;
const API_HEADERS = { "X-Picker-Token": TOKEN };
// names come from the incident's files (photo names, carriage numbers): escaped before they go into HTML
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
async function jsonOf(r) {  // the server answers JSON, errors included; anything else is reported as it came
  const text = await r.text();
  try { return JSON.parse(text); } catch (e) { return { error: `HTTP ${r.status}: ${text.slice(0, 200)}` }; }
}
const cv = $("photo-canvas"), ctx = cv.getContext("2d");

function status(msg, error) { const s = $("status"); s.textContent = msg; s.className = error ? "error" : ""; }
function key(o) { return o.carriage + "|" + o.point + "|" + o.view; }
function car() { return S.doc.cars.find((c) => c.number === S.car); }

async function load() {
  const r = await fetch("/api/state", { headers: API_HEADERS });
  const doc = await jsonOf(r);
  if (!r.ok) { status(doc.error || "cannot load", true); return; }
  S.doc = doc; S.manual = doc.manual.map((o) => Object.assign({}, o));
  S.rejected = (doc.rejected || []).map((o) => Object.assign({}, o));
  $("incident").textContent = doc.incident;
  $("photo-select").innerHTML = doc.photos.map((p) => `<option value="${esc(p.name)}">${esc(p.name)}</option>`).join("");
  $("car-select").innerHTML = doc.cars.map((c) => `<option value="${esc(c.number)}">${esc(c.number)} (${esc(c.type)})</option>`).join("");
  S.car = doc.cars[0].number;
  await selectPhoto(doc.photos[0].name);
  selectCar(S.car);
  const npred = doc.automatic.filter(predicted).length;
  status(`${doc.automatic.length} automatic (${npred} predicted from a pose or another photo), ` +
         `${doc.manual.length} manual points, ${S.rejected.length} rejected`);
}

function selectPhoto(name) {
  S.photo = S.doc.photos.find((p) => p.name === name);
  $("photo-select").value = name;
  return new Promise((resolve) => {
    const img = new Image();
    img.onload = () => { S.img = img; fit(); resolve(); };
    img.src = S.photo.url;
  });
}

function selectCar(number) {
  S.car = number; $("car-select").value = number; S.point = null;
  const c = car(), box = $("faces");
  box.innerHTML = "";
  for (const [face, f] of Object.entries(c.faces)) {
    const div = document.createElement("div"); div.className = face === "front" || face === "rear" ? "face end" : "face";
    div.innerHTML = `<h3>${esc(face)}</h3>`;
    const fc = document.createElement("canvas"); fc.id = "face-" + face; fc.width = f.width; fc.height = f.height;
    fc.dataset.face = face; div.appendChild(fc); box.appendChild(div);
    const im = new Image(); im.onload = () => { S.faceImgs[face] = im; drawFace(fc, face); }; im.src = f.url;
    fc.addEventListener("click", (ev) => {
      const r = fc.getBoundingClientRect(), sx = f.width / r.width;
      const u = (ev.clientX - r.left) * sx - 0.5, v = (ev.clientY - r.top) * sx - 0.5;
      let best = null, bd = 1e9;
      for (const [n, p] of Object.entries(f.points)) { const d = Math.hypot(p[0] - u, p[1] - v); if (d < bd) { bd = d; best = n; } }
      if (best && bd < 25 * sx) selectPoint(best);
    });
  }
  listPoints(); draw();
}

function selectPoint(name) { S.point = name; listPoints(); redrawFaces(); draw(); status(`point ${name}: click its place in the photo`); }

// an automatic point placed from its car's pose or carried from another photo, not found on a face
function predicted(o) { return o.method === "pose" || o.method === "carried"; }

function listPoints() {
  const c = car(), view = S.photo.name;
  $("points").innerHTML = c.points.map((n) => {
    const m = S.manual.find((o) => o.carriage === c.number && o.point === n && o.view === view);
    const a = S.doc.automatic.find((o) => o.carriage === c.number && o.point === n && o.view === view);
    const x = S.rejected.find((o) => o.carriage === c.number && o.point === n && o.view === view);
    const tag = m ? '<span class="tag manual">manual</span>' : x ? '<span class="tag rejected">rejected</span>'
      : a ? (predicted(a) ? '<span class="tag predicted" title="predicted from the car\'s pose or another photo: check it">predicted</span>'
                          : '<span class="tag auto">auto</span>') : "";
    return `<li data-point="${esc(n)}" class="${n === S.point ? "selected" : ""}">${esc(n)} <small>(${esc(c.point_faces[n].join(", "))})</small>${tag}</li>`;
  }).join("");
  for (const li of $("points").children) li.onclick = () => selectPoint(li.dataset.point);
}

function drawFace(fc, face) {
  const g = fc.getContext("2d"), f = car().faces[face], im = S.faceImgs[face];
  if (!im) return;
  g.drawImage(im, 0, 0);
  const r = Math.max(4, f.height / 14);
  for (const [n, p] of Object.entries(f.points)) {
    g.beginPath(); g.arc(p[0] + 0.5, p[1] + 0.5, n === S.point ? r * 1.6 : r, 0, 2 * Math.PI);
    g.lineWidth = 3; g.strokeStyle = n === S.point ? "#ffd54f" : "#ff1744"; g.stroke();
  }
}
function redrawFaces() { for (const fc of document.querySelectorAll(".face canvas")) drawFace(fc, fc.dataset.face); }

function fit() {
  const r = cv.getBoundingClientRect(); cv.width = r.width; cv.height = r.height;
  S.scale = Math.min(cv.width / S.img.width, cv.height / S.img.height);
  S.ox = (cv.width - S.img.width * S.scale) / 2; S.oy = (cv.height - S.img.height * S.scale) / 2; draw();
}
function zoomAt(f, sx, sy) { S.ox = sx - (sx - S.ox) * f; S.oy = sy - (sy - S.oy) * f; S.scale *= f; draw(); }
function toScreen(uv) { return [(uv[0] + 0.5) * S.scale + S.ox, (uv[1] + 0.5) * S.scale + S.oy]; }
function toImage(x, y) { return [(x - S.ox) / S.scale - 0.5, (y - S.oy) / S.scale - 0.5]; }

function draw() {
  if (!S.img) return;
  ctx.setTransform(1, 0, 0, 1, 0, 0); ctx.fillStyle = "#111"; ctx.fillRect(0, 0, cv.width, cv.height);
  ctx.imageSmoothingEnabled = S.scale < 2;
  ctx.drawImage(S.img, S.ox, S.oy, S.img.width * S.scale, S.img.height * S.scale);
  const view = S.photo.name, man = new Set(S.manual.map(key)), rej = new Set(S.rejected.map(key));
  ctx.font = "11px sans-serif";
  for (const o of S.doc.automatic) {
    if (o.view !== view) continue;
    const [x, y] = toScreen(o.uv), over = man.has(key(o)), mine = o.carriage === S.car;
    if (rej.has(key(o))) {  // rejected: a grey X
      ctx.strokeStyle = "#9e9e9e"; ctx.lineWidth = 2; ctx.beginPath();
      ctx.moveTo(x - 5, y - 5); ctx.lineTo(x + 5, y + 5); ctx.moveTo(x + 5, y - 5); ctx.lineTo(x - 5, y + 5); ctx.stroke();
      continue;
    }
    // measured (on a face, by its homography): a blue circle; predicted (from a pose, or carried from another
    // photo): a dashed amber one, the points most worth checking
    const pr = predicted(o);
    ctx.beginPath(); ctx.arc(x, y, 5, 0, 2 * Math.PI); ctx.lineWidth = 2; ctx.setLineDash(pr ? [3, 2] : []);
    ctx.strokeStyle = over ? "#777" : pr ? "#ffb74d" : "#2196f3"; ctx.stroke(); ctx.setLineDash([]);
    if (mine && o.point === S.point) { ctx.beginPath(); ctx.arc(x, y, 9, 0, 2 * Math.PI); ctx.strokeStyle = "#ffd54f"; ctx.stroke(); }
    if (mine) { ctx.fillStyle = "#90caf9"; ctx.fillText(o.point, x + 7, y - 6); }
  }
  for (const o of S.manual) {
    if (o.view !== view) continue;
    const [x, y] = toScreen(o.uv), mine = o.carriage === S.car;
    ctx.strokeStyle = mine && o.point === S.point ? "#ffd54f" : "#ff1744"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.moveTo(x - 7, y); ctx.lineTo(x + 7, y); ctx.moveTo(x, y - 7); ctx.lineTo(x, y + 7); ctx.stroke();
    ctx.fillStyle = "#ff8a80"; ctx.fillText(`${o.carriage}:${o.point}`, x + 8, y + 12);
  }
}

function pushUndo() { S.undo.push(JSON.stringify([S.manual, S.rejected])); S.dirty = true; }
function pick(uv) {
  if (!S.point) { status("pick a marked point on the model first", true); return; }
  const w = S.photo.width, h = S.photo.height;
  if (uv[0] < -0.5 || uv[1] < -0.5 || uv[0] > w - 0.5 || uv[1] > h - 0.5) { status("outside the photo", true); return; }
  pushUndo();
  const o = { carriage: S.car, point: S.point, view: S.photo.name, uv: [+uv[0].toFixed(2), +uv[1].toFixed(2)],
              source: "manual", confidence: 1.0 };
  S.manual = S.manual.filter((m) => key(m) !== key(o)); S.manual.push(o);
  S.rejected = S.rejected.filter((m) => key(m) !== key(o));  // picked now: no longer rejected
  listPoints(); draw(); status(`${o.carriage} ${o.point} at (${o.uv[0]}, ${o.uv[1]}) in ${o.view} — unsaved`);
}
function undo() {
  if (!S.undo.length) { status("nothing to undo"); return; }
  [S.manual, S.rejected] = JSON.parse(S.undo.pop()); listPoints(); draw(); status("undone — unsaved");
}
function removePick() {
  const k = S.car + "|" + S.point + "|" + S.photo.name;
  if (!S.manual.some((m) => key(m) === k)) { status("no manual pick of this point in this photo"); return; }
  pushUndo(); S.manual = S.manual.filter((m) => key(m) !== k); listPoints(); draw(); status("removed — unsaved");
}
function toggleReject() {
  if (!S.point) { status("select a point first", true); return; }
  const k = S.car + "|" + S.point + "|" + S.photo.name;
  const auto = S.doc.automatic.some((o) => key(o) === k);
  if (S.rejected.some((o) => key(o) === k)) {
    pushUndo(); S.rejected = S.rejected.filter((o) => key(o) !== k); listPoints(); draw();
    status(`${S.car} ${S.point}: automatic point kept — unsaved`); return;
  }
  if (!auto) { status("no automatic point of this point in this photo to reject", true); return; }
  if (S.manual.some((m) => key(m) === k)) { status("this point has a manual pick: remove it first (Del)", true); return; }
  pushUndo(); S.rejected.push({ carriage: S.car, point: S.point, view: S.photo.name, reason: "rejected in the picker" });
  listPoints(); draw(); status(`${S.car} ${S.point}: automatic point rejected — unsaved`);
}
async function save() {
  const r = await fetch("/api/save", { method: "POST", headers: Object.assign({ "Content-Type": "application/json" }, API_HEADERS),
                                      body: JSON.stringify({ observations: S.manual, rejected: S.rejected }) });
  const res = await jsonOf(r);
  if (!r.ok) { status(res.error || `HTTP ${r.status}`, true); return; }
  S.dirty = false; status(`saved ${res.n} manual points and ${res.n_rejected} rejections to ${res.saved}`);
}

// mouse: click picks, drag pans, wheel zooms
let down = null;
cv.addEventListener("mousedown", (e) => { down = { x: e.offsetX, y: e.offsetY, ox: S.ox, oy: S.oy, moved: false }; });
cv.addEventListener("mousemove", (e) => {
  if (!down) return;
  const dx = e.offsetX - down.x, dy = e.offsetY - down.y;
  if (Math.hypot(dx, dy) > 3) down.moved = true;
  if (down.moved) { S.ox = down.ox + dx; S.oy = down.oy + dy; draw(); }
});
cv.addEventListener("mouseup", (e) => { if (down && !down.moved) pick(toImage(e.offsetX, e.offsetY)); down = null; });
cv.addEventListener("wheel", (e) => { e.preventDefault(); zoomAt(e.deltaY < 0 ? 1.25 : 0.8, e.offsetX, e.offsetY); }, { passive: false });
window.addEventListener("keydown", (e) => {
  if ((e.ctrlKey || e.metaKey) && e.key === "z") { e.preventDefault(); undo(); }
  else if ((e.ctrlKey || e.metaKey) && e.key === "s") { e.preventDefault(); save(); }
  else if (e.key === "+" || e.key === "=") zoomAt(1.25, cv.width / 2, cv.height / 2);
  else if (e.key === "-") zoomAt(0.8, cv.width / 2, cv.height / 2);
  else if (e.key === "0") fit();
  else if (e.key === "Delete") removePick();
  else if (e.key === "r" || e.key === "R") toggleReject();
});
window.addEventListener("resize", () => S.img && fit());
window.addEventListener("beforeunload", (e) => { if (S.dirty) { e.preventDefault(); e.returnValue = ""; } });
$("zoom-in").onclick = () => zoomAt(1.25, cv.width / 2, cv.height / 2);
$("zoom-out").onclick = () => zoomAt(0.8, cv.width / 2, cv.height / 2);
$("zoom-fit").onclick = fit;
$("undo").onclick = undo; $("save").onclick = save; $("delete").onclick = removePick; $("reject").onclick = toggleReject;
$("photo-select").onchange = async (e) => { await selectPhoto(e.target.value); listPoints(); };
$("car-select").onchange = (e) => selectCar(e.target.value);
window.pickerState = S;  // for tests and debugging
load().catch((err) => status(String(err), true));
