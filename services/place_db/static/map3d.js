// The operator page's 3D view (three.js, vendored: no CDN). The page's script hands over
// every map it reads (event "fleetmap-map": the map and its token-carrying `get`); this
// draws each placed robot's cloud (GET /map/robots/R/cloud.bin, in R's own map frame,
// placed by transforms[R]; a drift-corrected robot's in the reference frame, bent with its
// keyframes), its keyframe track (GET /map/trajectories) and the verified
// overlaps (GET /map/lines), z up as in ROS. Orbit: left drag; pan: right drag; zoom: wheel.
// The page loads map3d.bundle.js: this file with three.js, built by scripts/build_map3d.sh.
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";

document.body.dataset.three3dMs = Math.round(performance.now());  // three.js loaded and parsed
const canvas = document.getElementById("view3d");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
// colours drawn as given (robot colours as in the pictures, image colours as sRGB bytes)
THREE.ColorManagement.enabled = false;
renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x15181c);
const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 1000);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, canvas);
controls.addEventListener("change", draw);
const clouds = new Map(); // robot -> {views, points: THREE.Points, data}
const tracks = new THREE.Group();
const links = new THREE.Group();
scene.add(tracks, links);
let colourBy = new URLSearchParams(location.hash.slice(1)).get("colour") || "robot";
document.getElementById("colour3d").value = colourBy;
let colours = {}, shownKey = null, fitted = false, busy = false;

function draw() { renderer.render(scene, camera); }

function resize() {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (canvas.width !== w || canvas.height !== h) renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  draw();
}
new ResizeObserver(resize).observe(canvas);

function rowMajor(T) {
  const m = new THREE.Matrix4();
  m.set(...T[0], ...T[1], ...T[2], ...T[3]);
  return m;
}

function material(robot) {
  if (colourBy === "image") return new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true });
  return new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, color: robotColour(robot) });
}
function robotColour(robot) { return new THREE.Color(...(colours[robot] || [0.6, 0.6, 0.6])); }

async function loadCloud(get, robot, want, inRef) {
  const q = inRef ? "?frame=reference" : "";
  const buf = await (await get("/map/robots/" + encodeURIComponent(robot) + "/cloud.bin" + q)).arrayBuffer();
  const n = buf.byteLength / 15;
  const geo = new THREE.BufferGeometry();
  geo.setAttribute("position", new THREE.BufferAttribute(new Float32Array(buf, 0, 3 * n), 3));
  geo.setAttribute("color", new THREE.BufferAttribute(new Uint8Array(buf, 12 * n, 3 * n), 3, true));
  geo.computeBoundingSphere();
  const old = clouds.get(robot);
  if (old) { scene.remove(old.points); old.points.geometry.dispose(); }
  const points = new THREE.Points(geo, material(robot));
  points.matrixAutoUpdate = false;
  scene.add(points);
  clouds.set(robot, { want, inRef, points });
}

function setLines(group, segments, colourOf) {
  for (const c of [...group.children]) { group.remove(c); c.geometry.dispose(); }
  for (const [key, pts] of segments) {
    const geo = new THREE.BufferGeometry().setFromPoints(pts.map((p) => new THREE.Vector3(...p)));
    const mat = new THREE.LineBasicMaterial({ color: colourOf(key) });
    group.add(group === links ? new THREE.LineSegments(geo, mat) : new THREE.Line(geo, mat));
  }
}

function fit() {
  scene.updateMatrixWorld();  // the clouds' placements, before the first render
  const box = new THREE.Box3();
  for (const { points } of clouds.values()) if (points.visible) box.expandByObject(points);
  if (box.isEmpty()) return;
  const c = box.getCenter(new THREE.Vector3()), r = Math.max(box.getSize(new THREE.Vector3()).length() / 2, 0.1);
  camera.position.set(c.x + 0.9 * r, c.y - 0.9 * r, c.z + 0.8 * r);
  camera.near = r / 100; camera.far = r * 100; camera.updateProjectionMatrix();
  controls.target.copy(c);
  controls.update();
  fitted = true;
}

async function show(m, get) {
  const views = Object.fromEntries(m.fleet.map((f) => [f.robot, f.views]));
  // a drift-corrected robot's map is bent: its cloud comes in the reference frame, each
  // point moved with its keyframe (cloud.bin?frame=reference), again after every solve
  const bent = new Set(m.fleet.filter((f) => f.drift_correction?.applied).map((f) => f.robot));
  const solved = m.fleet_graph?.solved_at ?? "";
  const want = (r) => views[r] + (bent.has(r) ? ":" + m.version + ":" + solved : "");
  const key = m.version + ":" + solved + ":" + m.fleet.map((f) => f.views).join(",");
  if (key === shownKey || busy) return;
  busy = true;
  try {
    // everything at once: the lines, the tracks and every cloud that changed
    const changed = m.robots.filter((r) => r in m.transforms && clouds.get(r)?.want !== want(r));
    const [lines, traj] = await Promise.all([
      get("/map/lines").then((r) => r.json()),
      get("/map/trajectories").then((r) => r.json()),
      ...changed.map((r) => loadCloud(get, r, want(r), bent.has(r))),
    ]);
    colours = lines.colours;
    for (const [r, c] of clouds) {
      const placed = r in m.transforms;
      c.points.visible = placed;
      if (placed) c.points.matrix.copy(c.inRef ? new THREE.Matrix4() : rowMajor(m.transforms[r]));
      c.points.material.dispose(); c.points.material = material(r);  // colours may be new
    }
    setLines(tracks, Object.entries(traj).map(([r, rows]) => [r, rows.map((row) => row.slice(1, 4))]), robotColour);
    setLines(links, [["overlaps", lines.overlaps.flatMap((l) => [l.slice(2, 5), l.slice(5, 8)])]], () => 0xffd21a);
    if (!fitted) fit();
    shownKey = key;
    resize();
    const drawn = [...clouds.entries()].filter(([, c]) => c.points.visible).map(([r]) => r);
    document.body.dataset.view3d = drawn.join(",");
    document.body.dataset.view3dCorrected = drawn.filter((r) => clouds.get(r).inRef).join(",");
    if (!document.body.dataset.first3dMs) document.body.dataset.first3dMs = Math.round(performance.now());
  } finally {
    busy = false;
  }
}

document.getElementById("colour3d").addEventListener("change", (e) => {
  colourBy = e.target.value;
  for (const [r, c] of clouds) { c.points.material.dispose(); c.points.material = material(r); }
  draw();
});
document.getElementById("fit3d").addEventListener("click", () => { fit(); draw(); });
window.addEventListener("fleetmap-map", (e) => show(e.detail.map, e.detail.get).catch((err) => {
  document.getElementById("error").textContent = "3D view: " + (err.message || err);
}));
if (window.fleetmapLast) show(window.fleetmapLast.map, window.fleetmapLast.get);
