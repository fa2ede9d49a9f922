// citytherm viewer (docs/viewer.md): a model picker, the model's newest thermal job in 3D from
// its 3D Tiles, a colour scale in °C, a clicked facade's figures and anomalies (OGC API -
// Features), and the jobs with their progress. Everything comes from the API that serves this
// page (`../` of the page), with the API key of this tab (`Authorization: Bearer`).
//
// Debug hook for tests and the console: `window.citythermViewer` (see the end of this file).
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { API, askKey, fetchBytes, fetchJson, forgetKey, keyFromAddress } from "./api.js";
import { colourOf, drawLegend } from "./colormap.js";
import { fillList, item, jobItem, showAnomalies, showFacade } from "./panel.js";
import { applyPoint, featureOf, featureTriangles, loadTileset, textureValue } from "./tiles.js";

const JOBS_EVERY_MS = 3000;
const ZERO_C_K = 273.15;
const $ = (id) => document.getElementById(id);

// -- 3D view ----------------------------------------------------------------------------------
const canvas = $("canvas");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(1); // screen pixels = canvas pixels: colours are the textures' own
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xdfe3e8);
scene.add(new THREE.HemisphereLight(0xffffff, 0x666666, 2.0)); // for the untextured (lit) grey
const sun = new THREE.DirectionalLight(0xffffff, 1.5);
sun.position.set(-1, -2, 3);
scene.add(sun);
const models = new THREE.Group();
scene.add(models);
const camera = new THREE.PerspectiveCamera(45, 1, 0.5, 1e5);
camera.up.set(0, 0, 1); // the scene frame is east-north-up
const controls = new OrbitControls(camera, canvas);
const render = () => renderer.render(scene, camera);
controls.addEventListener("change", render); // render on demand: no loop burning a core

function resize() {
  const { clientWidth: w, clientHeight: h } = canvas;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  render();
}
new ResizeObserver(resize).observe(canvas);

/** Point the camera at `target` from `eye` (scene frame), near/far to fit `size` metres. */
function look(eye, target, size) {
  camera.position.copy(eye);
  camera.near = Math.max(0.05, size / 2000);
  camera.far = size * 50 + eye.distanceTo(target);
  camera.updateProjectionMatrix();
  controls.target.copy(target);
  controls.update();
  render();
}

/**
 * The overview: the observed surfaces (those with a mean temperature; every building when there
 * is none), seen steeply from above, from the side they face (the sum of their outward normals; from the
 * south-west when that is vertical).
 */
function frameAll() {
  const { box, facing } = observedSurfaces();
  if (box.isEmpty()) box.setFromObject(models);
  if (box.isEmpty()) return;
  facing.z = 0;
  if (facing.lengthSq() < 1e-12) facing.set(-0.5, -0.85, 0);
  facing.normalize().multiplyScalar(0.6).setZ(0.8); // some 50° down: over the buildings across the street
  const size = Math.max(box.getSize(new THREE.Vector3()).length(), 10);
  const centre = box.getCenter(new THREE.Vector3());
  look(centre.clone().addScaledVector(facing, 1.1 * size), centre, size);
}

/** The box (scene frame) of the triangles of observed surfaces, and the area-weighted sum of
 * their outward normals (the NORMAL attribute: CityGML's orientation). */
function observedSurfaces() {
  const box = new THREE.Box3();
  const facing = new THREE.Vector3();
  const [a, b, c, n] = [0, 1, 2, 3].map(() => new THREE.Vector3());
  models.traverse((mesh) => {
    const info = mesh.userData.citytherm;
    if (!mesh.isMesh || !info?.featureAttribute) return;
    const means = info.content.tables.get(info.propertyTable)?.columns.meanTemperature;
    const { index, attributes } = mesh.geometry;
    const ids = attributes[info.featureAttribute];
    if (!means || !ids || !attributes.normal) return;
    const vertex = (k) => (index ? index.getX(k) : k);
    for (let k = 0; k < (index ? index.count : attributes.position.count); k += 3) {
      if (means[Math.round(ids.getX(vertex(k)))] === null) continue;
      for (const [v, j] of [[a, 0], [b, 1], [c, 2]]) {
        v.fromBufferAttribute(attributes.position, vertex(k + j)).applyMatrix4(mesh.matrixWorld);
        box.expandByPoint(v);
      }
      const area = n.crossVectors(b.sub(a), c.sub(a)).length() / 2;
      n.fromBufferAttribute(attributes.normal, vertex(k)).transformDirection(mesh.matrixWorld);
      facing.addScaledVector(n, area);
    }
  });
  return { box, facing };
}

// -- state --------------------------------------------------------------------------------------
const state = { modelId: null, model: null, loaded: null, display: null, unit: "K", theme: null };

function setStatus(text) {
  $("status").textContent = text;
}

function showMessage(text) {
  $("message").textContent = text ?? "";
  $("message").hidden = !text;
}

/** A value of the tileset's unit (kelvin, or counts) as text. */
function formatValue(v) {
  if (v === null || v === undefined || !Number.isFinite(v)) return "—";
  return state.unit === "K" ? `${(v - ZERO_C_K).toFixed(1)} °C` : `${v.toFixed(1)} counts`;
}

// -- models -------------------------------------------------------------------------------------
async function loadModels() {
  const { models: list } = await fetchJson("models");
  const select = $("model");
  select.replaceChildren(
    ...list.map((m) => {
      const label = m.status === "ready" ? m.name : `${m.name} (${m.status})`;
      const o = new Option(`${label} · #${m.id}`, String(m.id));
      o.disabled = m.status !== "ready";
      return o;
    }),
  );
  const wanted = new URL(location.href).searchParams.get("model");
  const ready = list.filter((m) => m.status === "ready");
  const pick = ready.find((m) => String(m.id) === wanted) ?? ready.find((m) => m.themes && Object.keys(m.themes).length) ?? ready[0];
  if (!pick) {
    showMessage("No city model yet: import one (POST /models or citytherm import).");
    return;
  }
  select.value = String(pick.id);
  select.onchange = () => openModel(list.find((m) => String(m.id) === select.value));
  await openModel(pick);
}

/** Load a model's tileset (its newest job with thermal textures) into the view. A content that
 * is gone (a newer job's tileset replaced this one while it loaded) loads the tileset again, once. */
async function openModel(model, retried = false) {
  const url = new URL(location.href);
  url.searchParams.set("model", String(model.id));
  history.replaceState(null, "", url);
  Object.assign(state, { modelId: model.id, model, loaded: null, seenJobs: null });
  $("reload").hidden = true;
  document.body.dataset.state = "loading";
  showMessage(null);
  clearInfo();
  try {
    const tilesetUrl = new URL(`models/${model.id}/3dtiles/tileset.json`, API);
    setStatus(`${model.name}: preparing the 3D tiles…`);
    const loaded = await loadTileset(tilesetUrl, models, {
      fetchJson,
      fetchBytes,
      onProgress: (done, total) => setStatus(`${model.name}: tiles ${done} / ${total}`),
    });
    if (state.modelId !== model.id) return; // another model was picked meanwhile
    const extras = loaded.tileset.asset?.extras?.citytherm ?? {};
    state.loaded = loaded;
    state.display = extras.display ?? null;
    state.unit = extras.value?.unit ?? "K";
    state.theme = extras.theme ?? null;
    showLegend();
    frameAll();
    setStatus(`${model.name} · theme ${state.theme ?? "?"} · ${loaded.contents.length} tiles`);
    document.body.dataset.state = "ready";
  } catch (err) {
    if (err.status === 404 && err.content && !retried && state.modelId === model.id) return openModel(model, true);
    models.clear();
    $("legend").hidden = true;
    render();
    const why = err.status === 404 ? "has no job with thermal textures yet" : `could not be loaded: ${err.message}`;
    showMessage(`Model ${model.name} ${why}.`);
    setStatus(model.name);
    document.body.dataset.state = "error";
  }
}

function showLegend() {
  const d = state.display;
  $("legend").hidden = !d;
  if (!d) return;
  $("legend-title").textContent = state.unit === "K" ? "°C" : "counts";
  const labels = { hi: $("legend-hi"), mid: $("legend-mid"), lo: $("legend-lo") };
  drawLegend($("legend-ramp"), labels, d.range[0], d.range[1], formatValue);
}

// -- picking and the info panel -----------------------------------------------------------------
const raycaster = new THREE.Raycaster();
let pressed = null;
canvas.addEventListener("pointerdown", (e) => (pressed = [e.clientX, e.clientY]));
canvas.addEventListener("pointerup", (e) => {
  // a click, not the end of an orbit drag
  if (pressed && Math.hypot(e.clientX - pressed[0], e.clientY - pressed[1]) < 4) pick(e.clientX, e.clientY);
  pressed = null;
});

/** Pick what is under the page position (x, y): fill the info panel. */
async function pick(x, y) {
  const rect = canvas.getBoundingClientRect();
  const ndc = new THREE.Vector2(((x - rect.left) / rect.width) * 2 - 1, -((y - rect.top) / rect.height) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  const hit = raycaster.intersectObject(models, true).find((h) => featureOf(h));
  if (!hit) return clearInfo();
  const { properties: p, mesh } = featureOf(hit);
  highlight(mesh.userData.citytherm.content, p.surface);
  const here = await textureValue(mesh, hit.uv).catch(() => null);
  $("info-hint").hidden = true;
  fillList($("info-figures"), [
    ["Building", p.building],
    ["Surface", p.surface],
    ["Class", p.surfaceClass],
    ["Mean", formatValue(p.meanTemperature)],
    ["Typical", formatValue(p.typicalTemperature)],
    ["Observed", p.observedShare === null ? "—" : `${Math.round(100 * p.observedShare)} %`],
    ["At this point", formatValue(here)],
  ]);
  $("info").dataset.surface = p.surface ?? "";
  const where = { building: p.building, surface: p.surface, model: state.model?.name, theme: state.theme };
  await Promise.all([showFacade(where), showAnomalies(where)]);
}

/** Outline the surface `gmlId` of a content (none: null). */
const outline = new THREE.LineSegments(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0x00e5ff }));
scene.add(outline);
function highlight(content, gmlId) {
  const tris = content ? featureTriangles(content, (f, t) => t?.columns.surface?.[f] === gmlId) : [];
  const faces = new THREE.BufferGeometry().setFromPoints(tris.flat());
  outline.geometry.dispose();
  outline.geometry = new THREE.EdgesGeometry(faces, 20);
  faces.dispose();
  render();
}

function clearInfo() {
  highlight(null);
  $("info-hint").hidden = false;
  $("info-figures").replaceChildren();
  fillList($("info-facade"), [["—", ""]]);
  $("info-anomalies").replaceChildren(item("—"));
  delete $("info").dataset.surface;
}

// -- jobs ---------------------------------------------------------------------------------------
async function refreshJobs() {
  try {
    if (!document.hidden) {
      const { jobs } = await fetchJson("jobs?limit=20");
      $("job-list").replaceChildren(...jobs.map((j) => jobItem(j, state.modelId)));
      if (!jobs.length) $("job-list").replaceChildren(item("no jobs"));
      noticeNewResults(jobs);
    }
  } catch (err) {
    $("job-list").replaceChildren(item(err.message));
  } finally {
    setTimeout(refreshJobs, JOBS_EVERY_MS);
  }
}

/** Offer to reload when a job of the shown model finished after the model was loaded. */
function noticeNewResults(jobs) {
  if (!state.loaded) return;
  const done = jobs.filter((j) => j.inputs?.model === state.modelId && j.status === "successful").map((j) => j.jobID);
  if (state.seenJobs === null) state.seenJobs = new Set(done);
  else if (done.some((id) => !state.seenJobs.has(id))) $("reload").hidden = false;
}

// -- debug hook (tests, console) -----------------------------------------------------------------
/**
 * Frame the surface with gml:id `gmlId`: the camera in front of its outer side, looking at its
 * middle from a distance that fits it, or at the ECEF point `focus` from `distance` metres.
 */
function frameSurface(gmlId, focus = null, distance = null) {
  for (const content of state.loaded?.contents ?? []) {
    const tris = featureTriangles(content, (f, t) => t?.columns.surface?.[f] === gmlId);
    if (!tris.length) continue;
    const centre = new THREE.Vector3();
    const normal = new THREE.Vector3();
    let area = 0;
    for (const [a, b, c] of tris) {
      const n = new THREE.Vector3().crossVectors(b.clone().sub(a), c.clone().sub(a));
      const w = n.length() / 2;
      normal.add(n);
      centre.add(a.clone().add(b).add(c).multiplyScalar(w / 3));
      area += w;
    }
    centre.divideScalar(area);
    normal.normalize();
    // the outer side: away from the middle of the building's vertices
    const building = featureProps(content, gmlId).building;
    const own = featureTriangles(content, (f, t) => t?.columns.building?.[f] === building).flat();
    const middle = own.reduce((s, v) => s.add(v), new THREE.Vector3()).divideScalar(own.length);
    if (normal.dot(centre.clone().sub(middle)) < 0) normal.negate();
    const extent = Math.max(...tris.flat().map((v) => v.distanceTo(centre)));
    const target = focus ? new THREE.Vector3(...applyPoint(state.loaded.sceneFromEcef, focus)) : centre;
    const d = distance ?? Math.max(3, (1.2 * extent) / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
    const eye = target.clone().addScaledVector(normal, d);
    if (Math.abs(normal.z) > 0.99) eye.y -= 0.01 * d; // straight down: keep lookAt defined
    look(eye, target, d + extent);
    return true;
  }
  return false;
}

function featureProps(content, gmlId) {
  for (const table of content.tables.values()) {
    const k = table?.columns.surface?.indexOf(gmlId) ?? -1;
    if (k >= 0) return Object.fromEntries(Object.entries(table.columns).map(([n, c]) => [n, c[k]]));
  }
  return {};
}

/** Page position `{x, y}` (CSS pixels) of an ECEF point, and whether it is in front of the camera. */
function project(x, y, z) {
  const p = new THREE.Vector3(...applyPoint(state.loaded.sceneFromEcef, [x, y, z]));
  const inFront = p.clone().applyMatrix4(camera.matrixWorldInverse).z < 0;
  p.project(camera);
  const rect = canvas.getBoundingClientRect();
  return { x: rect.left + ((p.x + 1) / 2) * rect.width, y: rect.top + ((1 - p.y) / 2) * rect.height, inFront };
}

window.citythermViewer = {
  project,
  frameSurface,
  frameAll,
  pick,
  /** `[r, g, b]` the colour scale gives a value in °C (or counts). */
  legendColour: (v) => {
    const [lo, hi] = state.display.range;
    return colourOf(state.unit === "K" ? v + ZERO_C_K : v, lo, hi);
  },
  state,
};

// -- start ------------------------------------------------------------------------------------
$("reload").onclick = () => state.model && openModel(state.model);
$("forget-key").onclick = () => {
  forgetKey();
  askKey().then(() => location.reload());
};
keyFromAddress();
resize();
refreshJobs();
loadModels().catch((err) => showMessage(`The models could not be listed: ${err.message}`));
