"""The operator page served at `/`: a shell holding no data. Its script reads `GET /map`
every two seconds with the operator token (from the address, `/#token=...`, or typed in
and kept for the tab's session) sent as a bearer header, and shows the overview picture,
the robots with their keyframes and merge state, the overlap matrix and why robots are not
merged, and the map in 3D (`static/map3d.js`, bundled with three.js into `map3d.bundle.js`
and served by the place database itself; `/#view=3d` shows it alone in the window). No
external asset: it works on an offline robot network."""

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<title>fleetmap live map</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body { font: 14px system-ui, sans-serif; margin: 1.2em; color: #222; }
h1 { font-size: 1.3em; margin: 0 0 .3em; }
#status { color: #555; margin-bottom: .8em; }
#error { color: #b00; font-weight: bold; }
main { display: flex; flex-wrap: wrap; gap: 1.5em; align-items: flex-start; }
section { min-width: 18em; }
table { border-collapse: collapse; margin-bottom: 1em; }
td, th { border: 1px solid #ccc; padding: .25em .5em; text-align: left; }
th { background: #f2f2f2; }
td.n { text-align: right; }
.reference { color: #063; font-weight: bold; } .merged { color: #063; } .unmerged { color: #a40; }
#overview { max-width: 640px; width: 100%; border: 1px solid #ddd; }
#login { display: none; margin: 1em 0; }
#view3d { width: 640px; height: 420px; display: block; border: 1px solid #ddd; }
body.only3d main > section:not(#s3d), body.only3d h1 { display: none; }
body.only3d #view3d { width: calc(100vw - 3em); height: calc(100vh - 7em); }
body.only3d { margin: .5em; }
</style></head>
<body>
<h1>fleetmap live map</h1>
<div id="status">loading...</div>
<div id="error"></div>
<form id="login"><label>Operator token <input id="token" type="password" autocomplete="off">
</label> <button>Show the map</button></form>
<main>
<section id="s3d"><canvas id="view3d"></canvas>
<div>colour <select id="colour3d"><option value="robot">by robot</option>
<option value="image">image colour</option></select> <button id="fit3d">fit</button>
drag: turn, right drag: pan, wheel: zoom; <a href="#view=3d">3D only</a></div></section>
<section><img id="overview" alt="overview of the live map (top-down)"></section>
<section>
<h2>Robots</h2>
<table id="robots"><thead><tr><th>robot</th><th>keyframes</th><th>views</th><th>state</th>
</tr></thead><tbody></tbody></table>
<h2>Unmerged</h2><ul id="unmerged"></ul>
<h2>Verified overlaps</h2><table id="matrix"></table>
<h2>Robot pairs</h2>
<table id="pairs"><thead><tr><th>pair</th><th>state</th><th>overlaps</th><th>inliers</th>
<th>aligner</th></tr></thead><tbody></tbody></table>
</section>
</main>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
let token = new URLSearchParams(location.hash.slice(1)).get("token")
  || sessionStorage.getItem("fleetmap-token") || "";
const hashArgs = new URLSearchParams(location.hash.slice(1));
if (hashArgs.has("token")) {  // the token leaves the address bar and the history once read
  sessionStorage.setItem("fleetmap-token", token);  // kept across #view=3d
  hashArgs.delete("token");
  const rest = hashArgs.toString();
  history.replaceState(null, "", location.pathname + location.search + (rest ? "#" + rest : ""));
}
let shown = null;
if (hashArgs.get("view") === "3d") {
  document.body.classList.add("only3d");
}
window.addEventListener("hashchange", () => location.reload());

function cell(row, text, cls) {
  const td = row.insertCell(); td.textContent = text; if (cls) td.className = cls; return td;
}
async function get(path) {
  const headers = token ? {authorization: "Bearer " + token} : {};
  const r = await fetch(path, {headers, cache: "no-store"});
  if (r.status === 401 || r.status === 403) { askToken(); throw new Error("token refused"); }
  if (!r.ok) throw new Error(path + ": HTTP " + r.status);
  return r;
}
function askToken() { $("login").style.display = "block"; }
$("login").addEventListener("submit", (e) => {
  e.preventDefault(); token = $("token").value;
  sessionStorage.setItem("fleetmap-token", token);
  $("login").style.display = "none"; refresh();
});
function render(m) {
  const placed = Object.keys(m.transforms).length;
  $("status").textContent = "map version " + m.version + ": " + placed + " of "
    + m.robots.length + " robots placed, reference " + (m.reference || "none")
    + (m.updated_at ? ", updated " + new Date(m.updated_at * 1000).toLocaleTimeString() : "");
  const rb = $("robots").tBodies[0]; rb.replaceChildren();
  for (const f of m.fleet) {
    const row = rb.insertRow(); row.dataset.robot = f.robot;
    cell(row, f.robot); cell(row, f.keyframes, "n"); cell(row, f.views, "n");
    cell(row, f.state, f.state);
  }
  const ul = $("unmerged"); ul.replaceChildren();
  for (const u of m.unmerged) {
    const li = document.createElement("li"); li.dataset.robot = u.robot;
    li.textContent = u.robot + ": " + u.reason; ul.appendChild(li);
  }
  if (!m.unmerged.length) ul.innerHTML = "<li>none</li>";
  const count = {};
  for (const e of m.overlaps) {
    count[e.robot_a + "|" + e.robot_b] = e.pairs; count[e.robot_b + "|" + e.robot_a] = e.pairs;
  }
  const t = $("matrix"); t.replaceChildren();
  const head = t.insertRow(); cell(head, "");
  for (const r of m.robots) cell(head, r);
  for (const a of m.robots) {
    const row = t.insertRow(); cell(row, a);
    for (const b of m.robots) cell(row, a === b ? "-" : (count[a + "|" + b] || 0), "n");
  }
  const pb = $("pairs").tBodies[0]; pb.replaceChildren();
  for (const p of m.pairs) {
    const row = pb.insertRow();
    cell(row, p.robot_a + " - " + p.robot_b); cell(row, p.status);
    cell(row, p.evidence, "n"); cell(row, p.inliers ?? "", "n"); cell(row, p.reason || "");
  }
}
async function refresh() {
  try {
    const m = await (await get("/map")).json();
    render(m);
    window.fleetmapLast = {map: m, get};  // the 3D view (map3d.js) draws it
    window.dispatchEvent(new CustomEvent("fleetmap-map", {detail: window.fleetmapLast}));
    const key = m.version + ":" + m.fleet.map((f) => f.views).join(",");
    if (key !== shown) {
      const png = await (await get("/map/overview.png")).blob();
      const old = $("overview").src;
      $("overview").src = URL.createObjectURL(png);
      if (old.startsWith("blob:")) URL.revokeObjectURL(old);
      shown = key;
    }
    $("error").textContent = "";
    document.body.dataset.version = m.version;
  } catch (err) {
    $("error").textContent = String(err.message || err);
  }
}
refresh();
setInterval(refresh, 2000);
</script>
<script type="module" src="/static/map3d/map3d.bundle.js"></script>
</body></html>
"""


def _csp(page: str) -> str:
    """The page's Content-Security-Policy: its own inline scripts (by hash) and nothing
    else runs; images from this service or the blobs the script makes; never framed."""
    import base64
    import hashlib
    import re

    hashes = [
        "'sha256-" + base64.b64encode(hashlib.sha256(body.encode()).digest()).decode() + "'"
        for body in re.findall(r"<script>(.*?)</script>", page, re.S)
    ]
    return (
        f"default-src 'none'; script-src 'self' {' '.join(hashes)}; "
        "style-src 'unsafe-inline'; img-src 'self' blob:; connect-src 'self'; "
        "frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
    )


CSP = _csp(PAGE)
