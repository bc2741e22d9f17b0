// massview viewer: shows streamed JPEG frames, sends fly-camera input and settings.
"use strict";
const mv = { ws: null, frames: 0, stats: null, hello: null, role: null, lastFrameSize: 0, keys: new Set(), look: [0, 0], wheel: 0 };
window.mv = mv;
const $ = (id) => document.getElementById(id);
let objectUrl = null;

function connect() {
  // the token of a viewer bound off loopback (also sent as a cookie; the query works without cookies)
  const token = new URLSearchParams(location.search).get("token");
  const query = token ? `?token=${encodeURIComponent(token)}` : "";
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${query}`);
  ws.binaryType = "blob";
  mv.ws = ws;
  ws.onopen = () => { $("status").textContent = "live"; };
  const role = (r) => { mv.role = r; $("status").textContent = r === "pilot" ? "live · steering" : "live · watching (another browser steers)"; };
  ws.onclose = () => { $("status").textContent = "reconnecting…"; setTimeout(connect, 1000); };
  ws.onmessage = (ev) => {
    if (typeof ev.data === "string") {
      const msg = JSON.parse(ev.data);
      if (msg.type === "hello") { hello(msg); role(msg.role); }
      else if (msg.type === "role") role(msg.role);
      else if (msg.type === "stats") showStats(msg);
      else if (msg.type === "error") { $("message").textContent = "rejected: " + msg.message; }
      return;
    }
    const url = URL.createObjectURL(ev.data);
    $("frame").src = url;
    if (objectUrl) URL.revokeObjectURL(objectUrl);
    objectUrl = url;
    mv.frames += 1;
    mv.lastFrameSize = ev.data.size;
    $("frameno").textContent = mv.frames;
  };
}

function fill(select, values, current) {
  select.innerHTML = "";
  for (const v of values) {
    const o = document.createElement("option");
    o.value = o.textContent = v;
    if (v === current) o.selected = true;
    select.appendChild(o);
  }
}

function hello(msg) {
  mv.hello = msg;
  fill($("decomposition"), msg.choices.decomposition, msg.settings.decomposition);
  $("decomposition").title = msg.choices.decomposition_note || "";  // why a system offers only some decompositions
  if (msg.choices.decomposition_note) $("message").textContent = msg.choices.decomposition_note;
  fill($("compositor"), msg.choices.compositor, msg.settings.compositor);
  $("tau").value = msg.settings.tau; $("tauv").textContent = msg.settings.tau;
  $("colorbyrank").checked = !!msg.settings.color_by_rank;
  if (msg.choices.colormap) fill($("colormap"), msg.choices.colormap, msg.settings.colormap);
  const shading = { exaggeration: msg.settings.exaggeration, sunaz: (msg.settings.sun || [])[0], sunalt: (msg.settings.sun || [])[1],
                    haze: msg.settings.haze };
  for (const [id, v] of Object.entries(shading)) if (v !== undefined) { $(id).value = v; $(id + "v").textContent = v; }
}

function showStats(s) {
  mv.stats = s;
  $("fps").textContent = s.fps.toFixed(1);
  $("tris").textContent = s.triangles_per_rank.map((t) => (t / 1000).toFixed(1) + "k").join(", ");
  $("imb").textContent = s.imbalance.toFixed(3);
  $("bytes").textContent = (s.bytes_per_frame / 1e6).toFixed(2) + " MB";
  if (s.m2) showReliefboards(s.m2);
  if (s.panel) showPanel(s.panel);
}

function showPanel(p) {  // a system's own table (T2 per rank, M1 per figure): {title, columns, rows of strings}
  const t = $("sysrows"); t.hidden = false;
  const cells = (tag, xs) => "<tr>" + xs.map((x) => `<${tag}>${String(x).replace(/[<>&]/g, "")}</${tag}>`).join("") + "</tr>";
  t.innerHTML = `<caption>${p.title.replace(/[<>&]/g, "")}</caption>` + cells("th", p.columns) + p.rows.map((r) => cells("td", r)).join("");
}

function showReliefboards(m) {  // M2: requests in flight and the angle-error histogram
  $("m2").hidden = false;
  $("m2boards").textContent = m.boards; $("m2orig").textContent = m.far_originals;
  $("m2flight").textContent = m.in_flight.join(", "); $("m2ans").textContent = m.answered;
  const c = $("m2hist"), g = c.getContext("2d"), n = m.angle_hist.length, top = Math.max(1, ...m.angle_hist);
  g.clearRect(0, 0, c.width, c.height); g.fillStyle = "#7fb3ff";
  m.angle_hist.forEach((v, i) => { const h = (v / top) * (c.height - 2); g.fillRect(i * c.width / n + 1, c.height - h, c.width / n - 2, h); });
}

function send(obj) { if (mv.ws && mv.ws.readyState === 1) mv.ws.send(JSON.stringify(obj)); }

function settings() {
  send({ type: "settings", decomposition: $("decomposition").value, compositor: $("compositor").value,
         tau: parseFloat($("tau").value), color_by_rank: $("colorbyrank").checked, ...shadingSettings() });
}
function shadingSettings() {  // terrain shading (view-time): exaggeration, sun, colour ramp, haze
  if (!mv.hello || !mv.hello.choices.colormap) return {};
  return { exaggeration: parseFloat($("exaggeration").value), sun: [parseFloat($("sunaz").value), parseFloat($("sunalt").value)],
           colormap: $("colormap").value, haze: parseFloat($("haze").value) };
}
for (const id of ["exaggeration", "sunaz", "sunalt", "haze"]) {
  $(id).addEventListener("input", () => { $(id + "v").textContent = $(id).value; });
  $(id).addEventListener("change", settings);
}
$("colormap").addEventListener("change", settings);
for (const id of ["decomposition", "compositor", "colorbyrank"]) $(id).addEventListener("change", settings);
$("tau").addEventListener("input", () => { $("tauv").textContent = $("tau").value; });
$("tau").addEventListener("change", settings);

const view = $("view");
let drag = null;
view.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; view.focus(); e.preventDefault(); });
window.addEventListener("mouseup", () => { drag = null; });
window.addEventListener("mousemove", (e) => {
  if (!drag) return;
  mv.look[0] += e.clientX - drag[0]; mv.look[1] += e.clientY - drag[1];
  drag = [e.clientX, e.clientY];
});
view.addEventListener("wheel", (e) => { mv.wheel += Math.sign(e.deltaY); e.preventDefault(); }, { passive: false });
const KEYS = { KeyW: [1, 0, 0], ArrowUp: [1, 0, 0], KeyS: [-1, 0, 0], ArrowDown: [-1, 0, 0], KeyD: [0, 1, 0], ArrowRight: [0, 1, 0],
               KeyA: [0, -1, 0], ArrowLeft: [0, -1, 0], KeyE: [0, 0, 1], KeyQ: [0, 0, -1] };
window.addEventListener("keydown", (e) => { if (KEYS[e.code] && e.target.tagName !== "SELECT") { mv.keys.add(e.code); e.preventDefault(); } });
window.addEventListener("keyup", (e) => { mv.keys.delete(e.code); });
window.addEventListener("blur", () => mv.keys.clear());

let last = performance.now();
setInterval(() => {
  const now = performance.now();
  const dt = Math.min((now - last) / 1000, 1);
  last = now;
  const move = [0, 0, 0];
  for (const k of mv.keys) for (let i = 0; i < 3; i++) move[i] += KEYS[k][i];
  for (let i = 0; i < 3; i++) move[i] = Math.max(-1, Math.min(1, move[i]));
  const look = mv.look.map((v) => Math.max(-4000, Math.min(4000, v)));
  const wheel = Math.max(-20, Math.min(20, mv.wheel));
  mv.look = [0, 0]; mv.wheel = 0;
  if (move.some((v) => v !== 0) || look.some((v) => v !== 0) || wheel !== 0) send({ type: "input", move, look, wheel, dt });
}, 33);

connect();
