// Validate glTF / GLB files with the Khronos glTF validator (npm gltf-validator).
// Usage: node validate.mjs FILE.glb [FILE.glb ...]
// Prints a JSON array with, per file, {file, numErrors, numWarnings, messages}; exit code 0 when
// every file was read (whatever the reports say: the caller judges them), 2 on a usage error.
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error("usage: node validate.mjs FILE.glb [FILE.glb ...]");
  process.exit(2);
}
const out = [];
for (const file of files) {
  const data = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(data, {
    uri: file,
    maxIssues: 0,
    externalResourceFunction: () => Promise.reject(new Error("external resources are not used")),
  });
  out.push({
    file,
    numErrors: report.issues.numErrors,
    numWarnings: report.issues.numWarnings,
    numInfos: report.issues.numInfos,
    messages: report.issues.messages,
    validatorVersion: report.validatorVersion,
  });
}
process.stdout.write(JSON.stringify(out));
