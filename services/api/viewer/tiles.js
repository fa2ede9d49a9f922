// A 3D Tiles 1.1 tileset with glTF content, as citytherm writes it (docs/3dtiles.md), loaded into a
// three.js scene: every content GLB at its place in a local east-north-up frame, with the feature
// ids and property tables of EXT_mesh_features / EXT_structural_metadata kept for picking.
//
// Frames (named target_from_source; 4x4 matrices as 16 float64 numbers, column-major like a
// 3D Tiles `transform`): a GLB vertex p (glTF y-up) is in ECEF at
//   ecef_from_tile · Y_UP_TO_Z_UP · p,   ecef_from_tile = root.transform · ... · leaf.transform,
// and the scene frame is the root tile's east-north-up frame (z up, metres, origin at the root's
// ECEF origin): scene_from_ecef = inverse(root.transform). The product scene_from_ecef ·
// ecef_from_tile is formed in float64 here, so the large ECEF numbers cancel before anything goes
// to the GPU as float32.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
/** glTF y-up -> 3D Tiles z-up: (x, y, z) -> (x, -z, y), column-major. */
export const Y_UP_TO_Z_UP = [1, 0, 0, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1];

/** `a · b` of two column-major 4x4 matrices (float64). */
export function multiply(a, b) {
  const out = new Array(16).fill(0);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  }
  return out;
}

/** The inverse of a rigid transform (rotation + translation), column-major. */
export function rigidInverse(m) {
  const out = [...IDENTITY];
  for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) out[c * 4 + r] = m[r * 4 + c]; // R^T
  for (let r = 0; r < 3; r++) out[12 + r] = -(out[r] * m[12] + out[4 + r] * m[13] + out[8 + r] * m[14]);
  return out;
}

/** `m · (x, y, z, 1)` -> [x, y, z] (float64). */
export function applyPoint(m, [x, y, z]) {
  return [0, 1, 2].map((r) => m[r] * x + m[4 + r] * y + m[8 + r] * z + m[12 + r]);
}

/** East-north-up frame at an ECEF point (fallback for a root without `transform`; the up
 * direction is the geocentric one, within 0.2° of the ellipsoid normal). */
function ecefFromEnu([x, y, z]) {
  const lon = Math.atan2(y, x);
  const lat = Math.atan2(z, Math.hypot(x, y));
  const [sl, cl, sp, cp] = [Math.sin(lon), Math.cos(lon), Math.sin(lat), Math.cos(lat)];
  return [-sl, cl, 0, 0, -sp * cl, -sp * sl, cp, 0, cp * cl, cp * sl, sp, 0, x, y, z, 1];
}

/** Every tile with content: `{uri, ecefFromTile}`, depth first. */
function contentTiles(root) {
  const out = [];
  const walk = (tile, ecefFromParent) => {
    const ecefFromTile = tile.transform ? multiply(ecefFromParent, tile.transform) : ecefFromParent;
    for (const c of tile.content ? [tile.content] : tile.contents ?? []) out.push({ uri: c.uri, ecefFromTile });
    for (const child of tile.children ?? []) walk(child, ecefFromTile);
  };
  walk(root, IDENTITY);
  return out;
}

// Component types of EXT_structural_metadata scalar properties -> typed arrays.
const TYPED = {
  FLOAT32: Float32Array, FLOAT64: Float64Array, INT8: Int8Array, UINT8: Uint8Array,
  INT16: Int16Array, UINT16: Uint16Array, INT32: Int32Array, UINT32: Uint32Array,
};
const OFFSETS = { UINT8: Uint8Array, UINT16: Uint16Array, UINT32: Uint32Array };

/**
 * Property table `index` of a glTF's EXT_structural_metadata, decoded: `{className, count,
 * columns}` with one array per property (strings; numbers with offset/scale applied and
 * `noData` as null). STRING and SCALAR properties only (what citytherm writes).
 */
export async function readPropertyTable(parser, index) {
  const ext = parser.json.extensions?.EXT_structural_metadata;
  const table = ext?.propertyTables?.[index];
  if (!table) return null;
  const cls = ext.schema.classes[table.class];
  const view = (i) => parser.getDependency("bufferView", i); // an ArrayBuffer of the view
  const columns = {};
  for (const [name, prop] of Object.entries(table.properties)) {
    const def = cls.properties[name];
    const values = await view(prop.values);
    if (def.type === "STRING") {
      const offsets = new OFFSETS[prop.stringOffsetType ?? "UINT32"](await view(prop.stringOffsets));
      const text = new TextDecoder();
      const bytes = new Uint8Array(values);
      columns[name] = Array.from({ length: table.count }, (_, k) =>
        text.decode(bytes.subarray(offsets[k], offsets[k + 1])),
      );
    } else if (def.type === "SCALAR" && TYPED[def.componentType]) {
      const raw = new TYPED[def.componentType](values, 0, table.count);
      const offset = prop.offset ?? def.offset ?? 0;
      const scale = prop.scale ?? def.scale ?? 1;
      columns[name] = Array.from(raw, (v) => (v === def.noData ? null : offset + scale * v));
    }
  }
  return { className: table.class, count: table.count, columns };
}

/** The value image (PNG bytes) of a primitive's property texture, or null. */
function valueTextureOf(json, primitiveDef) {
  const k = primitiveDef.extensions?.EXT_structural_metadata?.propertyTextures?.[0];
  const ext = json.extensions?.EXT_structural_metadata;
  if (k === undefined || !ext) return null;
  const texture = ext.propertyTextures[k];
  const prop = Object.values(texture.properties)[0];
  const def = ext.schema.classes[texture.class].properties[Object.keys(texture.properties)[0]];
  const image = json.images[json.textures[prop.index].source];
  return { bufferView: image.bufferView, mimeType: image.mimeType, channels: prop.channels ?? [0], def };
}

/**
 * One loaded content: its three.js object (placed in the scene frame), the parser (to read
 * buffer views later), the decoded property table of its feature ids, and per mesh the
 * feature id attribute and value texture (`mesh.userData.citytherm`).
 */
async function loadContent(loader, fetchBytes, url, sceneFromGltf) {
  const bytes = await fetchBytes(url);
  const gltf = await loader.parseAsync(bytes, url.href.replace(/[^/]*$/, ""));
  const { parser } = gltf;
  const object = gltf.scene;
  object.matrixAutoUpdate = false;
  object.matrix.fromArray(sceneFromGltf);
  object.updateMatrixWorld(true);
  const content = { url: url.href, object, parser, tables: new Map() };
  const meshes = [];
  object.traverse((o) => o.isMesh && meshes.push(o));
  for (const mesh of meshes) {
    const assoc = parser.associations.get(mesh);
    const prim = parser.json.meshes[assoc.meshes].primitives[assoc.primitives ?? 0];
    const set = prim.extensions?.EXT_mesh_features?.featureIds?.[0];
    if (set && !content.tables.has(set.propertyTable)) {
      content.tables.set(set.propertyTable, await readPropertyTable(parser, set.propertyTable));
    }
    mesh.userData.citytherm = {
      content,
      featureAttribute: set && set.attribute !== undefined ? `_feature_id_${set.attribute}` : null,
      propertyTable: set?.propertyTable,
      valueTexture: valueTextureOf(parser.json, prim),
    };
  }
  return content;
}

/**
 * Load a tileset and all its content into `group` (cleared first).
 * `fetchJson(url)` and `fetchBytes(url)` fetch with the API key; `onProgress(done, total)`.
 * Returns `{tileset, sceneFromEcef, ecefFromScene, contents}`.
 */
export async function loadTileset(tilesetUrl, group, { fetchJson, fetchBytes, onProgress }) {
  const tileset = await fetchJson(tilesetUrl);
  const root = tileset.root;
  const box = root.boundingVolume?.box;
  const ecefFromScene = root.transform ?? ecefFromEnu(box ? box.slice(0, 3) : [0, 0, 0]);
  const sceneFromEcef = rigidInverse(ecefFromScene);
  const tiles = contentTiles(root).filter((t) => /\.glb$/i.test(t.uri));
  const loader = new GLTFLoader();
  group.clear();
  const contents = [];
  let done = 0;
  onProgress?.(done, tiles.length);
  // a few at a time: the GLBs of a large model must not all be in flight at once
  const queue = [...tiles];
  const worker = async () => {
    for (let t = queue.shift(); t; t = queue.shift()) {
      const sceneFromGltf = multiply(multiply(sceneFromEcef, t.ecefFromTile), Y_UP_TO_Z_UP);
      const content = await loadContent(loader, fetchBytes, new URL(t.uri, tilesetUrl), sceneFromGltf).catch(
        (err) => {
          err.content = t.uri; // a content failed (the tileset itself loaded)
          throw err;
        },
      );
      group.add(content.object);
      contents.push(content);
      onProgress?.(++done, tiles.length);
    }
  };
  await Promise.all(Array.from({ length: 4 }, worker));
  return { tileset, sceneFromEcef, ecefFromScene, contents };
}

/** What a ray hit on a loaded content: `{mesh, feature, properties}` (the property table's row). */
export function featureOf(hit) {
  const info = hit.object.userData.citytherm;
  if (!info?.featureAttribute || !hit.face) return null;
  const attr = hit.object.geometry.getAttribute(info.featureAttribute);
  if (!attr) return null;
  const feature = Math.round(attr.getX(hit.face.a));
  const table = info.content.tables.get(info.propertyTable);
  const properties = {};
  for (const [name, column] of Object.entries(table?.columns ?? {})) properties[name] = column[feature];
  return { mesh: hit.object, feature, properties };
}

const decodedImages = new Map(); // content url + buffer view -> ImageData

/**
 * The property texture's value at texture coordinate `uv` of a hit mesh (e.g. the temperature
 * in kelvin: offset + scale · DN / 65535 for a normalized UINT16), or null (no texture, noData).
 */
export async function textureValue(mesh, uv) {
  const info = mesh.userData.citytherm;
  const tex = info?.valueTexture;
  if (!tex || !uv) return null;
  const key = `${info.content.url}#${tex.bufferView}`;
  if (!decodedImages.has(key)) {
    const bytes = await info.content.parser.getDependency("bufferView", tex.bufferView);
    const bitmap = await createImageBitmap(new Blob([bytes], { type: tex.mimeType }), {
      colorSpaceConversion: "none",
      premultiplyAlpha: "none",
    });
    const canvas = new OffscreenCanvas(bitmap.width, bitmap.height);
    const ctx = canvas.getContext("2d", { willReadFrequently: true });
    ctx.drawImage(bitmap, 0, 0);
    decodedImages.set(key, ctx.getImageData(0, 0, bitmap.width, bitmap.height));
  }
  const img = decodedImages.get(key);
  // glTF: (0, 0) is the image's top-left corner, v runs downwards (three keeps flipY false)
  const x = Math.min(img.width - 1, Math.max(0, Math.floor(uv.x * img.width)));
  const y = Math.min(img.height - 1, Math.max(0, Math.floor(uv.y * img.height)));
  const p = 4 * (y * img.width + x);
  let dn = 0;
  tex.channels.forEach((c, k) => (dn += img.data[p + c] << (8 * k))); // little-endian bytes
  const { def } = tex;
  if (dn === def.noData) return null;
  const max = def.componentType === "UINT8" ? 255 : 65535;
  const v = def.normalized ? dn / max : dn;
  return (def.offset ?? 0) + (def.scale ?? 1) * v;
}

/** Triangles of a content whose feature passes `test(featureId, propertyTable)`, in the scene
 * frame: `[[a, b, c], ...]` of THREE.Vector3 (for framing a surface). */
export function featureTriangles(content, test) {
  const out = [];
  content.object.traverse((mesh) => {
    const info = mesh.userData.citytherm;
    if (!mesh.isMesh || !info?.featureAttribute) return;
    const table = info.content.tables.get(info.propertyTable);
    const ids = mesh.geometry.getAttribute(info.featureAttribute);
    const pos = mesh.geometry.getAttribute("position");
    const index = mesh.geometry.index;
    const n = index ? index.count : pos.count;
    for (let k = 0; k < n; k += 3) {
      const v = [0, 1, 2].map((j) => (index ? index.getX(k + j) : k + j));
      const f = Math.round(ids.getX(v[0]));
      if (!test(f, table)) continue;
      out.push(v.map((i) => new THREE.Vector3().fromBufferAttribute(pos, i).applyMatrix4(mesh.matrixWorld)));
    }
  });
  return out;
}
