// Copy the three.js modules the /viewer page imports from node_modules/three into the API package
// (services/api/viewer/vendor/three/, keeping three's folder layout so that the modules' relative
// imports resolve; the page's import map resolves the bare `three`). Run after `npm ci`:
//   node vendor.mjs [OUT_DIR]        (default: ../../services/api/viewer/vendor)
// The list matches VENDOR_FILES of services/api/routes_viewer.py.
import { copyFileSync, mkdirSync, rmSync } from "node:fs";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = resolve(process.argv[2] ?? join(here, "../../services/api/viewer/vendor"));
const three = join(here, "node_modules/three");
const files = [
  "build/three.module.js",
  "build/three.core.js",
  "examples/jsm/loaders/GLTFLoader.js", // imports the two utils below
  "examples/jsm/controls/OrbitControls.js",
  "examples/jsm/utils/BufferGeometryUtils.js",
  "examples/jsm/utils/SkeletonUtils.js",
  "LICENSE",
];
rmSync(join(out, "three"), { recursive: true, force: true });
for (const f of files) {
  const target = join(out, "three", f === "LICENSE" ? "LICENSE.txt" : f);
  mkdirSync(dirname(target), { recursive: true });
  copyFileSync(join(three, f), target);
}
console.log(`vendor: ${files.length} files of three into ${out}/three`);
