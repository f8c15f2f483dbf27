// Workbench picker, control points (docs/picker.md): the map pane (orthophoto or DEM hillshade in the project CRS,
// buildings and railway lines over it, zoom and pan, scale bar, north arrow), control points clicked in the photo
// and on the map or typed, saved to control_points.json, and the georef stage run on request with its residuals.
// Map pixel convention as the photo's: pixel (0, 0) is the centre of the top-left pixel; on screen
// x = (u + 0.5) * M.scale + M.ox. The server sends crs_from_pixel: [E, N] = A @ [u, v, 1] (north-up).
// Uses picker.js's globals: S, $, esc, status, draw, jsonOf, API_HEADERS.
"use strict";
(() => {  // one scope: picker.js's globals (pushUndo, key, ...) are not overwritten
const M = { doc: null, img: null, scale: 1, ox: 0, oy: 0, cps: null, sel: null, result: null, dirty: false,
            mode: "marks", undo: [], loadError: null, tsel: null };
const mcv = $("map-canvas"), mctx = mcv.getContext("2d");
const POST = (url, body) => fetch(url, { method: "POST", headers: Object.assign({ "Content-Type": "application/json" }, API_HEADERS),
                                          body: JSON.stringify(body) }).then(async (r) => ({ ok: r.ok, status: r.status, res: await jsonOf(r) }));

function crsOf(uv) { const A = M.doc.crs_from_pixel; return [A[0][0] * uv[0] + A[0][2], A[1][1] * uv[1] + A[1][2]]; }
function mapUv(en) { const A = M.doc.crs_from_pixel; return [(en[0] - A[0][2]) / A[0][0], (en[1] - A[1][2]) / A[1][1]]; }
function mScreen(uv) { return [(uv[0] + 0.5) * M.scale + M.ox, (uv[1] + 0.5) * M.scale + M.oy]; }
function mImage(x, y) { return [(x - M.ox) / M.scale - 0.5, (y - M.oy) / M.scale - 0.5]; }
function cp() { return M.cps && M.cps.points.find((p) => p.name === M.sel); }
function info(msg, error) { status(msg, error); }

async function loadMap() {
  const [a, b] = await Promise.all([fetch("/api/map", { headers: API_HEADERS }), fetch("/api/control_points", { headers: API_HEADERS })]);
  const ma = await jsonOf(a), cps = await jsonOf(b);
  if (!b.ok) { M.loadError = cps.error; info(cps.error || "cannot read control_points.json", true); M.cps = { crs: "", points: [] }; }
  else M.cps = cps;
  M.cps.track_picks = M.cps.track_picks || [];
  fillLines(ma && ma.railways ? ma.railways : []); renderTracks();
  if (!a.ok || !ma.available) {  // no map: typed coordinates still work
    M.loadError = ma.reason || ma.error || `HTTP ${a.status}`; $("cp-info").textContent = "no map: " + M.loadError;
    renderTable(); noMap(); return;
  }
  M.doc = ma;
  $("cp-info").textContent = "loading the map…";
  await new Promise((resolve) => { const im = new Image(); im.onload = () => { M.img = im; resolve(); }; im.onerror = resolve; im.src = ma.url; });
  renderTable(); mapFit();
  // shown once the map is drawn (the tests wait for it)
  $("cp-info").textContent = `map: ${ma.source}; ${ma.pixel_size_m.toFixed(2)} m per pixel, ${ma.crs}` +
    (M.img ? "" : "; the map image did not load") + (ma.notes && ma.notes.length ? "; " + ma.notes.join("; ") : "");
}

function noMap() {
  const r = mcv.getBoundingClientRect(); mcv.width = r.width; mcv.height = r.height;
  mctx.fillStyle = "#111"; mctx.fillRect(0, 0, mcv.width, mcv.height);
  mctx.fillStyle = "#bbb"; mctx.font = "13px sans-serif";
  mctx.fillText("No map for this incident: type the control points' coordinates below.", 16, 28);
  mctx.fillText("A map needs terrain.ortho (a georeferenced orthophoto) or terrain.dem in project.toml.", 16, 48);
}
function mapFit() {
  const r = mcv.getBoundingClientRect(); mcv.width = r.width; mcv.height = r.height;
  if (!M.doc) return;
  M.scale = Math.min(mcv.width / M.doc.width, mcv.height / M.doc.height);
  M.ox = (mcv.width - M.doc.width * M.scale) / 2; M.oy = (mcv.height - M.doc.height * M.scale) / 2; drawMap();
}
function mapZoomAt(f, sx, sy) { M.ox = sx - (sx - M.ox) * f; M.oy = sy - (sy - M.oy) * f; M.scale *= f; drawMap(); }

function mpath(pts, close) {
  mctx.beginPath();
  pts.forEach((p, i) => { const [x, y] = mScreen(p); if (i) mctx.lineTo(x, y); else mctx.moveTo(x, y); });
  if (close) mctx.closePath();
}
function drawMap() {
  if (!M.doc) return;
  mctx.setTransform(1, 0, 0, 1, 0, 0); mctx.fillStyle = "#111"; mctx.fillRect(0, 0, mcv.width, mcv.height);
  mctx.imageSmoothingEnabled = M.scale < 2;
  if (M.img) mctx.drawImage(M.img, M.ox, M.oy, M.doc.width * M.scale, M.doc.height * M.scale);
  mctx.lineWidth = 1.5; mctx.strokeStyle = "#ffab40"; mctx.fillStyle = "rgba(255, 171, 64, 0.15)";
  for (const b of M.doc.buildings) { mpath(b.ring, true); mctx.fill(); mctx.stroke(); }
  for (const r of M.doc.railways) {
    mctx.strokeStyle = "#202020"; mctx.lineWidth = 4; mpath(r.line); mctx.stroke();
    mctx.strokeStyle = "#f5f5f5"; mctx.lineWidth = 2; mctx.setLineDash([8, 8]); mpath(r.line); mctx.stroke(); mctx.setLineDash([]);
  }
  mctx.font = "12px sans-serif";
  for (const p of (M.cps ? M.cps.points : [])) {
    if (!p.coords) continue;
    const [x, y] = mScreen(mapUv(p.coords)), sel = p.name === M.sel, r = residualOf(p.name);
    mctx.strokeStyle = r && r.flagged ? "#ff4081" : sel ? "#ffd54f" : "#ffee58"; mctx.lineWidth = sel ? 3 : 2;
    mctx.beginPath(); mctx.moveTo(x - 8, y); mctx.lineTo(x + 8, y); mctx.moveTo(x, y - 8); mctx.lineTo(x, y + 8); mctx.stroke();
    mctx.beginPath(); mctx.arc(x, y, 5, 0, 2 * Math.PI); mctx.stroke();
    mctx.fillStyle = "#fff59d"; mctx.fillText(p.name, x + 9, y - 7);
  }
  drawCameras(); drawScaleBar(); drawNorth();
}
function drawCameras() {
  if (!M.result) return;
  for (const c of M.result.cameras) {
    const [x, y] = mScreen(c.map_uv), px = M.doc.pixel_size_m;
    const az = c.azimuth_deg * Math.PI / 180 - (M.doc.grid_convergence_deg * Math.PI / 180);  // on the grid-north-up map
    mctx.strokeStyle = "#00e5ff"; mctx.fillStyle = "#00e5ff"; mctx.lineWidth = 2;
    mctx.beginPath(); mctx.moveTo(x, y); mctx.lineTo(x + 40 * Math.sin(az), y - 40 * Math.cos(az)); mctx.stroke();
    mctx.beginPath(); mctx.arc(x, y, 4, 0, 2 * Math.PI); mctx.fill();
    if (c.cov_centre_enu_m2) {  // the horizontal 95 % ellipse (2 degrees of freedom: 2.448 sigma)
      const C = c.cov_centre_enu_m2, a = C[0][0], b = C[0][1], d = C[1][1], tr = (a + d) / 2, det = Math.sqrt(Math.max(((a - d) / 2) ** 2 + b * b, 0));
      const l1 = tr + det, l2 = Math.max(tr - det, 0), ang = 0.5 * Math.atan2(2 * b, a - d), k = 2.448 / px * M.scale;
      mctx.beginPath(); mctx.ellipse(x, y, Math.max(Math.sqrt(l1) * k, 2), Math.max(Math.sqrt(l2) * k, 2), -ang, 0, 2 * Math.PI); mctx.stroke();
    }
    mctx.fillText(c.name, x + 8, y + 14);
  }
}
function drawScaleBar() {
  const mPerScreen = M.doc.pixel_size_m / M.scale, target = mcv.width / 5 * mPerScreen;
  const p = Math.pow(10, Math.floor(Math.log10(target))), len = [5, 2, 1].map((k) => k * p).find((v) => v <= target) || p;
  const w = len / mPerScreen, x = 14, y = mcv.height - 16;
  mctx.fillStyle = "rgba(0, 0, 0, 0.55)"; mctx.fillRect(x - 6, y - 20, w + 60, 28);
  mctx.strokeStyle = "#fff"; mctx.lineWidth = 2; mctx.beginPath();
  mctx.moveTo(x, y - 6); mctx.lineTo(x, y); mctx.lineTo(x + w, y); mctx.lineTo(x + w, y - 6); mctx.stroke();
  mctx.fillStyle = "#fff"; mctx.fillText(len >= 1000 ? `${len / 1000} km` : `${len} m`, x + w + 6, y);
}
function drawNorth() {  // true north: grid north turned by minus the grid convergence
  const g = -M.doc.grid_convergence_deg * Math.PI / 180, x = mcv.width - 30, y = 40;
  mctx.save(); mctx.translate(x, y); mctx.rotate(g);
  mctx.fillStyle = "rgba(0, 0, 0, 0.55)"; mctx.beginPath(); mctx.arc(0, 0, 22, 0, 2 * Math.PI); mctx.fill();
  mctx.fillStyle = "#fff"; mctx.beginPath(); mctx.moveTo(0, -17); mctx.lineTo(7, 9); mctx.lineTo(0, 4); mctx.lineTo(-7, 9); mctx.closePath(); mctx.fill();
  mctx.restore(); mctx.fillStyle = "#fff"; mctx.fillText("N", x - 4, y + 36);
}

// ---- control points ---------------------------------------------------------------------------------------
function residualOf(name, view) {
  if (!M.result) return null;
  const rs = M.result.residuals.filter((r) => r.point === name && (!view || r.view === view));
  if (!rs.length) return null;
  return rs.reduce((a, b) => ((b.error_px || 0) > (a.error_px || 0) ? b : a));
}
function pushUndo() { M.undo.push(JSON.stringify({ points: M.cps.points, track_picks: M.cps.track_picks })); M.dirty = true; }
function select(name) {
  M.sel = name; const p = cp();
  if (name !== null) { M.tsel = null; renderTracks(); }
  $("cp-name").value = p ? p.name : "";
  if (p && p.coords) {
    if ($("cp-coord-kind").value === "wgs84") { $("cp-x").value = p.lat !== undefined ? p.lat.toFixed(8) : ""; $("cp-y").value = p.lon !== undefined ? p.lon.toFixed(8) : ""; }
    else { $("cp-x").value = p.coords[0].toFixed(3); $("cp-y").value = p.coords[1].toFixed(3); }
    $("cp-h").value = p.coords[2].toFixed(3);
  } else { $("cp-x").value = ""; $("cp-y").value = ""; $("cp-h").value = ""; }
  $("cp-sigma").value = p ? p.sigma_m : ""; $("cp-h-override").checked = !!(p && p.h_own);
  renderTable(); drawMap(); draw();
}
function newPoint() {
  pushUndo();
  let k = M.cps.points.length + 1; while (M.cps.points.some((p) => p.name === `cp_${k}`)) k++;
  M.cps.points.push({ name: `cp_${k}`, coords: null, sigma_m: 0.5, kind: "", pixels: {} });
  select(`cp_${k}`); info(`cp_${k}: click the landmark in the photo and on the map (or type its coordinates and press Set)`);
}
// picks on the track (track_picks in control_points.json, docs/gis.md): points anywhere along one rail (or the track
// centre) of one line of the railway layer, in one photo; georef fits the camera to them point to line
function tp() { return M.tsel !== null ? M.cps.track_picks[M.tsel] : null; }
function fillLines(lines) {
  const opts = lines.map((r) => `<option value="${esc(r.id)}">${esc(r.name ? `${r.id} (${r.name})` : r.id)}</option>`);
  $("tp-line").innerHTML = lines.length > 1 ? opts.join("") : `<option value="">${lines.length ? esc(lines[0].id) + " (the only line)" : "(the layer's only line)"}</option>`;
}
function renderTracks() {
  if (!M.cps) return;
  const view = S.photo ? S.photo.name : "", t = tp();
  const here = M.cps.track_picks.filter((x) => x.photo === view);
  $("tp-info").textContent = `track picks: ${M.cps.track_picks.length} (${here.length} in this photo, ` +
    `${here.reduce((a, x) => a + x.pixels.length, 0)} points)` + (t ? `; picking: ${t.line || "the line"}, ${t.rail}, ${t.pixels.length} point(s) in ${t.photo} (Esc ends)` : "");
}
function newTrackPick() {
  if (!S.photo || !M.cps) return;
  pushUndo();
  M.cps.track_picks.push({ photo: S.photo.name, line: $("tp-line").value, rail: $("tp-rail").value, pixels: [] });
  M.sel = null; renderTable();
  M.tsel = M.cps.track_picks.length - 1; renderTracks(); draw();
  info(`track pick in ${S.photo.name}: click points along the ${$("tp-rail").value === "centre" ? "track centre" : $("tp-rail").value + " rail"}` +
       " anywhere on it (spread them out); Esc ends");
}
function endTrackPick() { if (M.tsel === null) return; M.tsel = null; renderTracks(); draw(); info("track pick ended — unsaved"); }
function removeTrackPick() {  // the one being picked, else the last one in this photo
  let i = M.tsel;
  if (i === null && S.photo) for (let k = M.cps.track_picks.length - 1; k >= 0 && i === null; k--) if (M.cps.track_picks[k].photo === S.photo.name) i = k;
  if (i === null) { info("no track pick in this photo", true); return; }
  pushUndo(); M.cps.track_picks.splice(i, 1); M.tsel = null; renderTracks(); draw(); info("track pick deleted — unsaved");
}
function trackClick(t, uv) {
  if (t.photo !== S.photo.name) { info(`this track pick is in ${t.photo}: show that photo, or end it (Esc)`, true); return; }
  const w = S.photo.width, h = S.photo.height;
  if (uv[0] < -0.5 || uv[1] < -0.5 || uv[0] > w - 0.5 || uv[1] > h - 0.5) { info("outside the photo", true); return; }
  pushUndo(); t.pixels.push([+uv[0].toFixed(2), +uv[1].toFixed(2)]); renderTracks(); draw();
  info(`track pick: ${t.pixels.length} point(s) on ${t.line || "the line"} (${t.rail}) — unsaved`);
}
function photoClick(uv) {
  const t = tp();
  if (t) { trackClick(t, uv); return; }
  const p = cp();
  if (!p) { info("control points: press New point (N) or choose one in the table first", true); return; }
  const w = S.photo.width, h = S.photo.height;
  if (uv[0] < -0.5 || uv[1] < -0.5 || uv[0] > w - 0.5 || uv[1] > h - 0.5) { info("outside the photo", true); return; }
  pushUndo(); p.pixels[S.photo.name] = [+uv[0].toFixed(2), +uv[1].toFixed(2)];
  renderTable(); draw(); info(`${p.name} at (${p.pixels[S.photo.name].join(", ")}) in ${S.photo.name}` + (p.coords ? " — unsaved" : ": now click it on the map"));
}
async function place(body, how) {
  const p = cp();
  if (!p) { info("control points: press New point (N) first", true); return; }
  const { ok, res } = await POST("/api/locate", body);
  if (!ok) { info(res.error, true); return; }
  pushUndo();
  const own = $("cp-h-override").checked && $("cp-h").value.trim() !== "" && isFinite(+$("cp-h").value);
  let h = own ? +$("cp-h").value : res.dem_height_m;
  if (h === null || h === undefined) { info((res.dem_note || "no DEM height here") + ": type the height and tick 'own height'", true); M.undo.pop(); return; }
  p.coords = [+res.e.toFixed(3), +res.n.toFixed(3), +h.toFixed(3)]; p.lat = res.lat; p.lon = res.lon; p.h_own = own;
  p.dem_height_m = res.dem_height_m;
  if ($("cp-sigma").value.trim() !== "" && +$("cp-sigma").value > 0) p.sigma_m = +$("cp-sigma").value;
  select(p.name);
  info(`${p.name} ${how}: E ${res.e.toFixed(2)}, N ${res.n.toFixed(2)}, h ${h.toFixed(2)} m (${own ? "own height" : "DEM"}) — unsaved`);
}
function mapClick(uv) {
  if (!M.doc) return;
  let [e, n] = crsOf(uv), snapped = "", best = 8 / M.scale * M.doc.pixel_size_m;  // 8 screen pixels, in metres
  const [e0, n0] = [e, n];
  for (const b of M.doc.buildings) for (const q of b.ring_crs) {  // the nearest building corner close by: snap to it
    const d = Math.hypot(q[0] - e0, q[1] - n0);
    if (d < best) { best = d; e = q[0]; n = q[1]; snapped = ` (snapped to a corner of building ${b.id})`; }
  }
  place({ e, n, from: "map" }, "on the map" + snapped);
}
function setTyped() {
  const x = +$("cp-x").value, y = +$("cp-y").value;
  if ($("cp-x").value.trim() === "" || $("cp-y").value.trim() === "" || !isFinite(x) || !isFinite(y)) { info("type two numbers", true); return; }
  place($("cp-coord-kind").value === "wgs84" ? { lat: x, lon: y, from: "typed" } : { e: x, n: y, from: "typed" }, "typed");
}
function roof() {  // the height of the roof of the building whose footprint holds (or has as a corner) the point
  const p = cp();
  if (!p || !p.coords) { info("place the point on the map first", true); return; }
  const b = M.doc.buildings.find((x) => inside(p.coords, x.ring_crs) || x.ring_crs.some((q) => Math.hypot(q[0] - p.coords[0], q[1] - p.coords[1]) < 0.01));
  if (!b) { info("the point is not on a building's footprint", true); return; }
  const base = b.base_m !== null ? b.base_m : p.dem_height_m;
  if (base === null || base === undefined) { info("no base height for this building", true); return; }
  pushUndo(); p.coords[2] = +(base + b.height_m).toFixed(3); p.h_own = true; select(p.name);
  info(`${p.name}: roof of building ${b.id}, h ${p.coords[2]} m — unsaved`);
}
function inside(pt, ring) {
  let c = false;
  for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
    const [xi, yi] = ring[i], [xj, yj] = ring[j];
    if ((yi > pt[1]) !== (yj > pt[1]) && pt[0] < (xj - xi) * (pt[1] - yi) / (yj - yi) + xi) c = !c;
  }
  return c;
}
function rename() {
  const p = cp(), name = $("cp-name").value.trim();
  if (!p || !name || name === p.name) return;
  if (M.cps.points.some((q) => q.name === name)) { info(`a point is already called ${name}`, true); $("cp-name").value = p.name; return; }
  pushUndo(); p.name = name; M.sel = name; renderTable(); drawMap();
}
function removePoint() {
  if (!cp()) return;
  pushUndo(); M.cps.points = M.cps.points.filter((p) => p.name !== M.sel); select(null); info("point deleted — unsaved");
}
function unpick() {
  const p = cp();
  if (!p || !p.pixels[S.photo.name]) { info("no pick of this point in this photo"); return; }
  pushUndo(); delete p.pixels[S.photo.name]; renderTable(); draw(); info("pick removed — unsaved");
}
function document_() {
  const pts = M.cps.points.filter((p) => p.coords);
  const track = M.cps.track_picks.filter((t) => t.pixels.length).map((t) => {
    const o = { photo: t.photo, rail: t.rail, pixels: t.pixels }; if (t.line) o.line = t.line; if (t.gauge_m) o.gauge_m = t.gauge_m; return o; });
  return { crs: M.doc ? M.doc.crs : M.cps.crs, description: M.cps.description || "picked in the workbench picker",
           points: pts.map((p) => { const o = { name: p.name, coords: p.coords, sigma_m: p.sigma_m, pixels: p.pixels }; if (p.kind) o.kind = p.kind; return o; }),
           track_picks: track };
}
async function saveCps() {
  const unplaced = M.cps.points.filter((p) => !p.coords).map((p) => p.name);
  const { ok, res } = await POST("/api/control_points", document_());
  if (!ok) { info(res.error, true); return false; }
  M.dirty = false;
  info(`saved ${res.n} control points (${res.n_picks} photo picks) and ${res.n_track_picks || 0} track points to ${res.saved}` + (unplaced.length ? `; not saved (no coordinates yet): ${unplaced.join(", ")}` : ""));
  return true;
}
async function georef() {
  if (M.dirty && !(await saveCps())) return;
  info("georef running…");
  const { ok, res } = await POST("/api/georef", {});
  if (!ok) { M.result = null; $("cp-result").innerHTML = `<span class="flag">${esc(res.error)}</span>`; info("georef failed: see the panel", true); renderTable(); drawMap(); draw(); return; }
  M.result = res; renderResult(); renderTable(); drawMap(); draw();
  const nf = res.residuals.filter((r) => r.flagged).length;
  info(`georef (${res.route}): rms ${res.rms_px !== null ? res.rms_px.toFixed(2) : "-"} px, ${nf} pick(s) flagged`, nf > 0);
}
const f2 = (x, d) => (x === null || x === undefined ? "–" : (+x).toFixed(d === undefined ? 2 : d));
function renderResult() {
  const r = M.result, parts = [`<h4>Georef: route ${esc(r.route)}, rms ${f2(r.rms_px)} px / ${f2(r.rms_m, 3)} m, ${r.n_points} points, ${r.n_outliers || 0} outliers (${f2(r.duration_s, 1)} s)</h4>`];
  for (const c of r.cameras.slice(0, 12)) {
    const s = c.sigma_centre_enu_m;
    parts.push(`<div>${esc(c.name)}: E ${f2(c.centre_crs[0])}, N ${f2(c.centre_crs[1])}, h ${f2(c.centre_crs[2])} m (lat ${f2(c.lat, 7)}, lon ${f2(c.lon, 7)}); looking ${f2(c.azimuth_deg, 1)}&deg; from true north, ${f2(c.tilt_deg, 1)}&deg; down` +
      (s ? `; 1&sigma; E/N/U ${f2(s[0])} / ${f2(s[1])} / ${f2(s[2])} m, 95 % within ${f2(c.ci95_centre_max_m)} m; rotation 1&sigma; ${f2(c.sigma_rotation_deg, 3)}&deg;` : "; no uncertainty stated") + "</div>");
  }
  const pr = r.priors;  // the GPS / compass / camera.position_enu priors the stage used (georef/priors.py)
  if (pr && pr.used && pr.used.length) {
    const bits = [];
    if (pr.centre) bits.push(`centre from ${esc(pr.centre.source)} (1&sigma; E/N/U ${(pr.centre.sigma_enu_m || []).map((x) => f2(x, 1)).join(" / ")} m` +
      (pr.centre.fitted_minus_prior_m ? `; placed ${pr.centre.fitted_minus_prior_m.map((x) => f2(x, 1)).join(" / ")} m from it` : "") + ")");
    for (const h of pr.heading || []) bits.push(`compass of ${esc(h.photo)} ${f2(h.azimuth_deg, 1)}&deg; &plusmn; ${f2(h.sigma_deg, 0)}&deg;` +
      (h.fitted_deg !== undefined ? ` (placed at ${f2(h.fitted_deg, 1)}&deg;)` : ""));
    parts.push(`<div class="note">priors used: ${bits.join("; ")}</div>`);
  } else if (r.route === "single" || r.route === "panorama") parts.push(`<div class="note">no priors: the control points alone (no GPS or compass in the photos, no camera.position_enu)</div>`);
  if (r.cameras.length > 12) parts.push(`<div class="note">and ${r.cameras.length - 12} more cameras</div>`);
  const flagged = r.residuals.filter((x) => x.flagged);
  if (flagged.length) parts.push(`<div class="flag">do not fit (beyond ${r.limits.flag_sigmas} sigma of the point and ${r.limits.warn_point_px} px, or outliers): ` +
    flagged.map((x) => `${esc(x.point)} in ${esc(x.view)} ${f2(x.error_px, 1)} px / ${f2(x.error_m)} m`).join("; ") + "</div>");
  else parts.push(`<div class="ok">every pick fits (within ${r.limits.flag_sigmas} sigma of its point)</div>`);
  for (const w of r.warnings) parts.push(`<div class="warn">stage: ${esc(w)}</div>`);
  for (const n of r.layout_notes || []) parts.push(`<div class="warn">layout: ${esc(n)}</div>`);
  $("cp-result").innerHTML = parts.join("");
}
function renderTable() {
  if (!M.cps) return;
  const view = S.photo ? S.photo.name : "";
  const rows = M.cps.points.map((p) => {
    const r = residualOf(p.name, view) || residualOf(p.name), c = p.coords;
    const res = r ? `<span class="${r.flagged ? "flag" : "ok"}">${f2(r.error_px, 1)} px / ${f2(r.error_m)} m${r.inlier ? "" : " outlier"}</span>` : "";
    return `<tr data-name="${esc(p.name)}" class="${p.name === M.sel ? "selected" : ""}"><td>${esc(p.name)}</td><td>${c ? f2(c[0]) : "–"}</td><td>${c ? f2(c[1]) : "–"}</td>` +
      `<td>${c ? f2(c[2]) : "–"}${p.h_own ? "*" : ""}</td><td>${f2(p.sigma_m)}</td><td>${Object.keys(p.pixels).length}${p.pixels[view] ? " (here)" : ""}</td><td>${res}</td></tr>`;
  });
  $("cp-table").innerHTML = `<tr><th>point</th><th>E</th><th>N</th><th>h (m)</th><th>&sigma; m</th><th>photos</th><th>residual</th></tr>` + rows.join("");
  for (const tr of $("cp-table").querySelectorAll("tr[data-name]")) tr.onclick = () => select(tr.dataset.name);
}
function drawPhoto(g, toScreen, view, scale) {  // called by picker.js draw(): the picks in this photo, residuals
  if (!M.cps || M.mode !== "control") return;
  g.font = "12px sans-serif";
  M.cps.track_picks.forEach((t, i) => {  // picks on the track: its points, joined in the order clicked
    if (t.photo !== view || !t.pixels.length) return;
    const sel = i === M.tsel, pts = t.pixels.map(toScreen);
    g.strokeStyle = sel ? "#ffab40" : "#ff9100"; g.lineWidth = sel ? 3 : 2; g.setLineDash([6, 4]);
    g.beginPath(); pts.forEach(([x, y], k) => (k ? g.lineTo(x, y) : g.moveTo(x, y))); g.stroke(); g.setLineDash([]);
    for (const [x, y] of pts) { g.beginPath(); g.arc(x, y, 4, 0, 2 * Math.PI); g.stroke(); }
    g.fillStyle = "#ffd180"; g.fillText(`${t.line || "track"} ${t.rail}`, pts[0][0] + 8, pts[0][1] + 16);
  });
  for (const p of M.cps.points) {
    const uv = p.pixels[view];
    if (!uv) continue;
    const [x, y] = toScreen(uv), r = residualOf(p.name, view), sel = p.name === M.sel;
    g.strokeStyle = r && r.flagged ? "#ff4081" : sel ? "#ffd54f" : "#ffee58"; g.lineWidth = sel ? 3 : 2;
    g.beginPath(); g.moveTo(x - 9, y); g.lineTo(x + 9, y); g.moveTo(x, y - 9); g.lineTo(x, y + 9); g.stroke();
    g.fillStyle = "#fff59d"; g.fillText(p.name, x + 10, y - 8);
    if (r && r.residual_px) {  // the pick to where the placed camera puts the point, times the magnifier
      const m = S.magnify, x2 = x + r.residual_px[0] * scale * m, y2 = y + r.residual_px[1] * scale * m;
      g.strokeStyle = r.flagged ? "#ff4081" : "#00e5ff"; g.beginPath(); g.moveTo(x, y); g.lineTo(x2, y2); g.stroke();
    }
  }
}
function setMode(mode) {
  M.mode = mode; $("mode-select").value = mode;
  $("model-pane").hidden = mode === "control"; $("map-pane").hidden = mode !== "control";
  if (typeof fit === "function" && S.img) fit();
  if (mode === "control") { if (!M.doc && !M.loadError) loadMap(); else if (M.doc) mapFit(); else noMap(); info("control points: New point (N), click it in the photo and on the map (or type it), Save, Run georef"); }
}
function undoCps() {
  if (!M.undo.length) { info("nothing to undo"); return; }
  const u = JSON.parse(M.undo.pop());
  M.cps.points = u.points; M.cps.track_picks = u.track_picks;
  if (M.tsel !== null && M.tsel >= M.cps.track_picks.length) M.tsel = null;
  select(cp() ? M.sel : null); renderTracks(); info("undone — unsaved");
}
function key(e) {
  if ((e.ctrlKey || e.metaKey) && e.key === "s") { e.preventDefault(); saveCps(); return true; }
  if ((e.ctrlKey || e.metaKey) && e.key === "z") { e.preventDefault(); undoCps(); return true; }
  if (e.key === "n" || e.key === "N") { newPoint(); return true; }
  if (e.key === "t" || e.key === "T") { newTrackPick(); return true; }
  if (e.key === "Escape" && M.tsel !== null) { endTrackPick(); return true; }
  if (e.key === "Delete") { unpick(); return true; }
  return false;
}

// map mouse: click places the selected point, drag pans, wheel zooms
let mdown = null;
mcv.addEventListener("mousedown", (e) => { mdown = { x: e.offsetX, y: e.offsetY, ox: M.ox, oy: M.oy, moved: false }; });
mcv.addEventListener("mousemove", (e) => {
  if (!mdown) return;
  const dx = e.offsetX - mdown.x, dy = e.offsetY - mdown.y;
  if (Math.hypot(dx, dy) > 3) mdown.moved = true;
  if (mdown.moved) { M.ox = mdown.ox + dx; M.oy = mdown.oy + dy; drawMap(); }
});
mcv.addEventListener("mouseup", (e) => { if (mdown && !mdown.moved) mapClick(mImage(e.offsetX, e.offsetY)); mdown = null; });
mcv.addEventListener("wheel", (e) => { e.preventDefault(); mapZoomAt(e.deltaY < 0 ? 1.25 : 0.8, e.offsetX, e.offsetY); }, { passive: false });
window.addEventListener("resize", () => { if (M.mode === "control") mapFit(); });
window.addEventListener("beforeunload", (e) => { if (M.dirty) { e.preventDefault(); e.returnValue = ""; } });
$("mode-select").onchange = (e) => setMode(e.target.value);
$("cp-new").onclick = newPoint; $("cp-delete").onclick = removePoint; $("cp-unpick").onclick = unpick;
$("cp-save").onclick = saveCps; $("cp-georef").onclick = georef; $("cp-set").onclick = setTyped; $("cp-roof").onclick = roof;
$("cp-name").onchange = rename;
$("cp-coord-kind").onchange = () => select(M.sel);
$("photo-select").addEventListener("change", () => setTimeout(() => { renderTable(); renderTracks(); }, 0));
$("tp-new").onclick = newTrackPick; $("tp-delete").onclick = removeTrackPick;

window.CP = { active: () => M.mode === "control", photoClick, drawPhoto, key, undo: undoCps, save: saveCps };
window.mapState = M;  // for tests and debugging
})();
