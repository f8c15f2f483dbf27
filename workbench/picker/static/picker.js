// Workbench marked-point picker. Pixel convention (docs/conventions.md): pixel (0, 0) is the centre of the
// top-left pixel, so image pixel i covers [i - 0.5, i + 0.5]; on screen: x = (u + 0.5) * scale + ox.
"use strict";
const S = { doc: null, photo: null, car: null, point: null, manual: [], rejected: [], undo: [], img: null,
            scale: 1, ox: 0, oy: 0, faceImgs: {}, dirty: false,
            overlay: null,   // GET /api/overlay: the solve's outlines and predicted points (null before it answers)
            live: null,      // POST /api/pose: the selected carriage posed from its current picks
            liveSeq: 0, liveTimer: null,
            edgeMode: false, segs: [], drawing: null,  // Edges: two segments drawn along a corner's edges
            showOverlay: true, magnify: 1 };
const MIN_EDGE_ANGLE_DEG = 5, MIN_SEGMENT_PX = 2;  // as workbench/files/correspondences.py checks them
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
  await fetchOverlay();
  const npred = doc.automatic.filter(predicted).length;
  status(`${doc.automatic.length} automatic (${npred} predicted from a pose or another photo), ` +
         `${doc.manual.length} manual points, ${S.rejected.length} rejected`);
}

function selectPhoto(name) {
  S.photo = S.doc.photos.find((p) => p.name === name);
  $("photo-select").value = name;
  return new Promise((resolve) => {
    const img = new Image();
    img.onload = () => { S.img = img; fit(); resolve(); if (S.overlay) fetchOverlay(); requestLive(); };
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
  S.live = null; listPoints(); draw(); requestLive();
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
  if (S.showOverlay) drawOverlay(view);
  ctx.font = "11px sans-serif";
  for (const o of S.doc.automatic) {
    if (o.view !== view || (window.CP && window.CP.active())) continue;
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
    if (o.construction && mine) drawConstruction(o.construction.segments, o.uv, "#ffd54f");
  }
  if (S.segs.length || S.drawing) drawConstruction(S.drawing ? S.segs.concat([[S.drawing.a, S.drawing.b]]) : S.segs, null, "#eeff41");
  if (window.CP) window.CP.drawPhoto(ctx, toScreen, view, S.scale);  // map.js: the control points' picks
}

function pushUndo() { S.undo.push(JSON.stringify([S.manual, S.rejected])); S.dirty = true; }
function pick(uv, construction) {
  if (!S.point) { status("pick a marked point on the model first", true); return; }
  const w = S.photo.width, h = S.photo.height;
  if (uv[0] < -0.5 || uv[1] < -0.5 || uv[0] > w - 0.5 || uv[1] > h - 0.5) { status("outside the photo", true); return; }
  pushUndo();
  const o = { carriage: S.car, point: S.point, view: S.photo.name, uv: [+uv[0].toFixed(2), +uv[1].toFixed(2)],
              source: "manual", confidence: 1.0 };
  if (construction) { o.uv = [+uv[0].toFixed(3), +uv[1].toFixed(3)]; o.construction = construction; }
  S.manual = S.manual.filter((m) => key(m) !== key(o)); S.manual.push(o);
  S.rejected = S.rejected.filter((m) => key(m) !== key(o));  // picked now: no longer rejected
  listPoints(); draw(); changed();
  status(`${o.carriage} ${o.point} at (${o.uv[0]}, ${o.uv[1]}) in ${o.view}${construction ? edgeNote(construction) : ""} — unsaved`,
         construction && edgeGain(construction) > EDGE_GAIN_WARN);
}
function undo() {
  if (!S.undo.length) { status("nothing to undo"); return; }
  [S.manual, S.rejected] = JSON.parse(S.undo.pop()); listPoints(); draw(); changed(); status("undone — unsaved");
}
function removePick() {
  const k = S.car + "|" + S.point + "|" + S.photo.name;
  if (!S.manual.some((m) => key(m) === k)) { status("no manual pick of this point in this photo"); return; }
  pushUndo(); S.manual = S.manual.filter((m) => key(m) !== k); listPoints(); draw(); changed(); status("removed — unsaved");
}
function toggleReject() {
  if (!S.point) { status("select a point first", true); return; }
  const k = S.car + "|" + S.point + "|" + S.photo.name;
  const auto = S.doc.automatic.some((o) => key(o) === k);
  if (S.rejected.some((o) => key(o) === k)) {
    pushUndo(); S.rejected = S.rejected.filter((o) => key(o) !== k); listPoints(); draw(); changed();
    status(`${S.car} ${S.point}: automatic point kept — unsaved`); return;
  }
  if (!auto) { status("no automatic point of this point in this photo to reject", true); return; }
  if (S.manual.some((m) => key(m) === k)) { status("this point has a manual pick: remove it first (Del)", true); return; }
  pushUndo(); S.rejected.push({ carriage: S.car, point: S.point, view: S.photo.name, reason: "rejected in the picker" });
  listPoints(); draw(); changed(); status(`${S.car} ${S.point}: automatic point rejected — unsaved`);
}
async function save() {
  const r = await fetch("/api/save", { method: "POST", headers: Object.assign({ "Content-Type": "application/json" }, API_HEADERS),
                                      body: JSON.stringify({ observations: S.manual, rejected: S.rejected }) });
  const res = await jsonOf(r);
  if (!r.ok) { status(res.error || `HTTP ${r.status}`, true); return; }
  S.dirty = false; status(`saved ${res.n} manual points and ${res.n_rejected} rejections to ${res.saved}`);
  fetchOverlay();
}

// mouse: click picks, drag pans, wheel zooms
let down = null;
cv.addEventListener("mousedown", (e) => {
  if (S.edgeMode && !e.shiftKey) { const a = toImage(e.offsetX, e.offsetY); S.drawing = { a, b: a }; return; }
  down = { x: e.offsetX, y: e.offsetY, ox: S.ox, oy: S.oy, moved: false };
});
cv.addEventListener("mousemove", (e) => {
  if (S.drawing) { S.drawing.b = toImage(e.offsetX, e.offsetY); draw(); return; }
  if (!down) return;
  const dx = e.offsetX - down.x, dy = e.offsetY - down.y;
  if (Math.hypot(dx, dy) > 3) down.moved = true;
  if (down.moved) { S.ox = down.ox + dx; S.oy = down.oy + dy; draw(); }
});
cv.addEventListener("mouseup", (e) => {
  if (S.drawing) { S.drawing.b = toImage(e.offsetX, e.offsetY); endSegment(); return; }
  if (down && !down.moved) {
    if (window.CP && window.CP.active()) window.CP.photoClick(toImage(e.offsetX, e.offsetY));  // map.js: control points
    else if (S.edgeMode) status("edges: drag along an edge (Shift+drag pans)"); else pick(toImage(e.offsetX, e.offsetY));
  }
  down = null;
});
cv.addEventListener("wheel", (e) => { e.preventDefault(); zoomAt(e.deltaY < 0 ? 1.25 : 0.8, e.offsetX, e.offsetY); }, { passive: false });
window.addEventListener("keydown", (e) => {
  if (e.target && e.target.tagName === "INPUT") return;  // typing coordinates or a name
  if (window.CP && window.CP.active() && window.CP.key(e)) return;  // map.js handles its own keys
  if ((e.ctrlKey || e.metaKey) && e.key === "z") { e.preventDefault(); undo(); }
  else if ((e.ctrlKey || e.metaKey) && e.key === "s") { e.preventDefault(); save(); }
  else if (e.key === "+" || e.key === "=") zoomAt(1.25, cv.width / 2, cv.height / 2);
  else if (e.key === "-") zoomAt(0.8, cv.width / 2, cv.height / 2);
  else if (e.key === "0") fit();
  else if (e.key === "Delete") removePick();
  else if (e.key === "r" || e.key === "R") toggleReject();
  else if (e.key === "e" || e.key === "E") toggleEdges();
  else if (e.key === "Escape") { if (S.segs.length || S.drawing) { S.segs = []; S.drawing = null; draw(); status("edges: start again"); } else if (S.edgeMode) toggleEdges(); }
});
window.addEventListener("resize", () => S.img && fit());
window.addEventListener("beforeunload", (e) => { if (S.dirty) { e.preventDefault(); e.returnValue = ""; } });
$("zoom-in").onclick = () => zoomAt(1.25, cv.width / 2, cv.height / 2);
$("zoom-out").onclick = () => zoomAt(0.8, cv.width / 2, cv.height / 2);
$("zoom-fit").onclick = fit;
// in the control-point mode the header's Undo and Save act on the control points (map.js)
$("undo").onclick = () => (window.CP && window.CP.active() ? window.CP.undo() : undo());
$("save").onclick = () => (window.CP && window.CP.active() ? window.CP.save() : save()); $("delete").onclick = removePick; $("reject").onclick = toggleReject;
$("edges").onclick = toggleEdges;
$("show-overlay").onchange = (e) => { S.showOverlay = e.target.checked; draw(); };
$("magnify").onchange = (e) => { S.magnify = +e.target.value; draw(); };
$("photo-select").onchange = async (e) => { await selectPhoto(e.target.value); listPoints(); };
$("car-select").onchange = (e) => selectCar(e.target.value);
// ---- the solve's overlay, the live pose, and picks from two edges -----------------------------------------
function changed() { renderChecks(); requestLive(); }

// the picks the next solve would read: manual ones, and automatic ones neither rejected nor replaced
function currentPicks() {
  const man = new Set(S.manual.map(key)), rej = new Set(S.rejected.map(key));
  return S.manual.concat(S.doc.automatic.filter((o) => !man.has(key(o)) && !rej.has(key(o))));
}

async function fetchOverlay() {
  const r = await fetch("/api/overlay?view=" + encodeURIComponent(S.photo.name), { headers: API_HEADERS });
  const res = await jsonOf(r);
  if (!r.ok) { status(res.error || `overlay: HTTP ${r.status}`, true); return; }
  S.overlay = res; renderChecks(); draw();
}

// a pick against the solved pose: {pred, dist, limit, flagged}, or null (no solve, the car not posed there)
function solvedResidual(o) {
  const ov = S.overlay;
  if (!ov || !ov.available) return null;
  const pred = ((ov.predicted[o.view] || {})[o.carriage] || {})[o.point];
  if (!pred) return null;
  const dist = Math.hypot(pred[0] - o.uv[0], pred[1] - o.uv[1]);
  const limit = ov.flag_sigmas * Math.max(ov.pixel_sigma_px, o.sigma_px || 0);
  return { pred, dist, limit, flagged: dist > limit };
}

function requestLive() {
  clearTimeout(S.liveTimer);
  S.liveTimer = setTimeout(postLive, 120);
}
async function postLive() {
  if (!S.doc || !S.photo) return;
  const car = S.car, seq = ++S.liveSeq;
  // measured picks only: a point the finder predicted from a pose or another photo is no evidence of its own
  const obs = currentPicks().filter((o) => o.carriage === car && !predicted(o)).map((o) => {
    const x = { point: o.point, view: o.view, uv: o.uv }; if (o.sigma_px) x.sigma_px = o.sigma_px; return x; });
  if (obs.length < 4) { S.live = { carriage: car, pose: null, reason: `${obs.length} picks: a pose needs 4 in one photo (6 where the focal is unknown)` }; renderChecks(); draw(); return; }
  const r = await fetch("/api/pose", { method: "POST", headers: Object.assign({ "Content-Type": "application/json" }, API_HEADERS),
                                      body: JSON.stringify({ carriage: car, observations: obs, view: S.photo.name }) });
  const res = await jsonOf(r);
  if (seq !== S.liveSeq) return;  // a later request is under way
  S.live = r.ok ? Object.assign(res, { view: S.photo.name }) : { carriage: car, pose: null, reason: res.error || `HTTP ${r.status}` };
  renderChecks(); draw();
}

function polyline(pts) {
  ctx.beginPath();
  pts.forEach((p, i) => { const [x, y] = toScreen(p); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
  ctx.stroke();
}
function drawOverlay(view) {
  const ov = S.overlay;
  if (ov && ov.available && ov.view === view) {  // the solve's outlines: the selected car bright, carried dashed
    for (const c of ov.cars) {
      const lines = ov.outline[c.number];
      if (!lines) continue;
      ctx.strokeStyle = c.number === S.car ? "rgba(0, 229, 255, 0.95)" : "rgba(0, 229, 255, 0.5)";
      ctx.lineWidth = c.number === S.car ? 1.5 : 1; ctx.setLineDash(c.status === "carried" ? [6, 4] : []);
      for (const ln of lines) polyline(ln);
    }
    ctx.setLineDash([]);
  }
  const lv = S.live;
  if (lv && lv.pose && lv.carriage === S.car) {
    if (lv.view === view && lv.outline) {
      ctx.strokeStyle = "rgba(178, 255, 89, 0.8)"; ctx.lineWidth = 1; ctx.setLineDash([4, 3]);
      for (const ln of lv.outline) polyline(ln);
      ctx.setLineDash([]);
    }
    for (const q of lv.flagged) {  // a pick far from where the others put it: to the live pose's place for it
      if (q.view !== view || !q.residual_px) continue;
      const [x, y] = toScreen(q.uv), [x2, y2] = toScreen([q.uv[0] + q.residual_px[0], q.uv[1] + q.residual_px[1]]);
      ctx.strokeStyle = "#ff4081"; ctx.lineWidth = 2; ctx.setLineDash([4, 3]);
      ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x2, y2); ctx.stroke(); ctx.setLineDash([]);
      ctx.beginPath(); ctx.arc(x, y, 14, 0, 2 * Math.PI); ctx.stroke();
    }
    const picked = new Set(currentPicks().filter((o) => o.view === view && o.carriage === S.car).map((o) => o.point));
    ctx.font = "11px sans-serif";
    for (const [n, p] of Object.entries(lv.predicted[view] || {})) {  // where the other points should fall
      if (picked.has(n)) continue;
      const [x, y] = toScreen(p.uv), rad = Math.min(Math.max(4, 2 * (p.sigma_px || 0) * S.scale), 150);
      // a point the car itself hides: dimmer, dashed
      ctx.strokeStyle = n === S.point ? "#ffd54f" : p.in_sight === false ? "rgba(178, 255, 89, 0.45)" : "#b2ff59";
      ctx.lineWidth = 1.5; ctx.setLineDash(p.in_sight === false ? [2, 3] : []);
      ctx.beginPath(); ctx.arc(x, y, rad, 0, 2 * Math.PI); ctx.stroke();
      ctx.beginPath(); ctx.moveTo(x - 3, y); ctx.lineTo(x + 3, y); ctx.moveTo(x, y - 3); ctx.lineTo(x, y + 3); ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = p.in_sight === false ? "rgba(204, 255, 144, 0.5)" : "#ccff90"; ctx.fillText(n, x + rad + 2, y + 4);
    }
  }
  for (const o of currentPicks()) {  // each pick to where the solved pose puts it
    if (o.view !== view) continue;
    const res = solvedResidual(o);
    if (!res) continue;
    const [x, y] = toScreen(o.uv), m = S.magnify;
    const x2 = x + (res.pred[0] - o.uv[0]) * S.scale * m, y2 = y + (res.pred[1] - o.uv[1]) * S.scale * m;
    ctx.strokeStyle = res.flagged ? "#ff4081" : "#00e5ff"; ctx.lineWidth = res.flagged ? 2.5 : 1.5;
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x2, y2); ctx.stroke();
    ctx.beginPath(); ctx.arc(x2, y2, 2, 0, 2 * Math.PI); ctx.fillStyle = ctx.strokeStyle; ctx.fill();
    if (res.flagged) { ctx.beginPath(); ctx.arc(x, y, 12, 0, 2 * Math.PI); ctx.stroke(); }
  }
}

function renderChecks() {
  const box = $("checks"), ov = S.overlay, lv = S.live, parts = [];
  if (ov && !ov.available) parts.push(`<div class="note">Solve: ${esc(ov.reason)}</div>`);
  if (ov && ov.available) {
    const all = currentPicks().map((o) => Object.assign({ o }, solvedResidual(o))).filter((r) => r.pred);
    const flagged = all.filter((r) => r.flagged).sort((a, b) => b.dist - a.dist);
    parts.push(`<h4>Solve (${esc(ov.solved_utc)}): <span class="${flagged.length ? "flag" : "ok"}">${flagged.length} of ${all.length} picks flagged</span>
      <span class="note">(residual beyond ${ov.flag_sigmas} sigma, ${(ov.flag_sigmas * ov.pixel_sigma_px).toFixed(1)} px)</span></h4>`);
    if (ov.stale) parts.push(`<div class="note">${esc(ov.stale)}</div>`);
    parts.push("<ul>" + flagged.map((r) => `<li class="flag" data-go="${esc(JSON.stringify([r.o.view, r.o.carriage, r.o.point]))}">${esc(r.o.carriage)} ${esc(r.o.point)} in ${esc(r.o.view)}: ${r.dist.toFixed(1)} px (${esc(r.o.source)}${r.o.method ? ", " + esc(r.o.method) : ""})</li>`).join("") + "</ul>");
  }
  if (lv && lv.carriage === S.car) {
    if (!lv.pose) parts.push(`<div class="note">Live pose of ${esc(S.car)}: ${esc(lv.reason)}</div>`);
    else {
      const f = Object.entries(lv.focal).map(([v, x]) => `${esc(v)} ${x.focal_px.toFixed(0)} px${x.sigma_px !== undefined ? ` &plusmn; ${x.sigma_px.toFixed(0)}` : ""}`).join(", ");
      parts.push(`<h4 class="live">Live pose of ${esc(S.car)} from ${lv.n_used} of ${lv.n_picks} picks: rms ${lv.rms_px.toFixed(2)} px${lv.checked ? "" : " (not checked: no more picks than the pose needs)"}</h4><div class="note">focal: ${f}${lv.not_used.length ? `; no camera or focal for the picks in ${esc(lv.not_used.join(", "))}` : ""}</div>`);
      if (lv.flagged.length) parts.push("<ul>" + lv.flagged.map((p) => `<li class="flag" data-go="${esc(JSON.stringify([p.view, S.car, p.point]))}">${esc(p.point)} in ${esc(p.view)}: ${p.off_the_others_px === null ? "far" : p.off_the_others_px.toFixed(1) + " px"} from where the other picks put it (left out of the live pose)</li>`).join("") + "</ul>");
    }
  }
  box.innerHTML = parts.join("");
  for (const li of box.querySelectorAll("li[data-go]")) li.onclick = () => goTo(...JSON.parse(li.dataset.go));
}
async function goTo(view, car, point) {
  if (S.photo.name !== view) await selectPhoto(view);
  if (S.car !== car) selectCar(car);
  selectPoint(point);
  const o = currentPicks().find((x) => x.view === view && x.carriage === car && x.point === point);
  if (o) { const f = Math.max(4 / S.scale, 1); S.scale *= f; const [x, y] = toScreen(o.uv); S.ox += cv.width / 2 - x; S.oy += cv.height / 2 - y; draw(); }
}

// Edges: two segments drawn along a corner's two edges; the pick is where their lines cross
function toggleEdges() {
  S.edgeMode = !S.edgeMode; S.segs = []; S.drawing = null;
  $("edges").style.background = S.edgeMode ? "#eeff41" : "";
  status(S.edgeMode ? "edges: drag along the first edge of the corner (Esc: start again; Shift+drag pans)" : "edges off");
  draw();
}
function intersect(a, b) {  // as workbench/files/correspondences.py lines_intersection
  const d1 = [a[1][0] - a[0][0], a[1][1] - a[0][1]], d2 = [b[1][0] - b[0][0], b[1][1] - b[0][1]];
  const n1 = Math.hypot(...d1), n2 = Math.hypot(...d2), cross = d1[0] * d2[1] - d1[1] * d2[0];
  if (!n1 || !n2 || !cross) return [null, 0];
  const angle = Math.asin(Math.min(1, Math.abs(cross) / (n1 * n2))) * 180 / Math.PI;
  const k = ((b[0][0] - a[0][0]) * d2[1] - (b[0][1] - a[0][1]) * d2[0]) / cross;
  return [[a[0][0] + k * d1[0], a[0][1] + k * d1[1]], angle];
}
// How far the crossing moves for a pixel's error across either edge: 1 / sin(angle between them). Two edges at a
// shallow angle (the two bottom edges at a near corner seen at a grazing angle) put the corner far off: say so.
const EDGE_GAIN_WARN = 3;  // 19.5 degrees
function edgeGain(c) { const a = intersect(c.segments[0], c.segments[1])[1]; return 1 / Math.sin(a * Math.PI / 180); }
function edgeNote(c) {
  const a = intersect(c.segments[0], c.segments[1])[1], g = edgeGain(c);
  return ` (from two edges ${a.toFixed(0)} deg apart${g > EDGE_GAIN_WARN ? `: a pixel off across an edge moves it ${g.toFixed(1)} px; edges closer to square are safer` : ""})`;
}
function endSegment() {
  const r2 = (p) => [+p[0].toFixed(2), +p[1].toFixed(2)];
  const seg = [r2(S.drawing.a), r2(S.drawing.b)];
  S.drawing = null;
  if (Math.hypot(seg[1][0] - seg[0][0], seg[1][1] - seg[0][1]) < MIN_SEGMENT_PX) { draw(); status("edges: drag along the edge (a click draws nothing; Shift+drag pans)", true); return; }
  S.segs.push(seg);
  if (S.segs.length < 2) { draw(); status("edges: now drag along the second edge"); return; }
  const segs = S.segs; S.segs = [];
  const [x, angle] = intersect(segs[0], segs[1]);
  if (!x || angle < MIN_EDGE_ANGLE_DEG) { draw(); status(`edges: the two edges are ${angle.toFixed(1)} deg apart; draw two edges that meet at a corner`, true); return; }
  pick(x, { method: "edges", segments: segs });
}
function drawConstruction(segs, x, colour) {
  ctx.strokeStyle = colour; ctx.lineWidth = 2;
  for (const s of segs) polyline(s);
  if (!x && segs.length === 2) x = intersect(segs[0], segs[1])[0];
  if (!x) return;
  ctx.setLineDash([3, 3]); ctx.lineWidth = 1;
  for (const s of segs) {  // each segment's line on to the corner
    const near = Math.hypot(s[0][0] - x[0], s[0][1] - x[1]) < Math.hypot(s[1][0] - x[0], s[1][1] - x[1]) ? s[0] : s[1];
    polyline([near, x]);
  }
  ctx.setLineDash([]);
}
window.pickerState = S;  // for tests and debugging
load().catch((err) => status(String(err), true));
