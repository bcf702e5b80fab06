// Validates glTF binaries with the Khronos glTF validator (npm `gltf-validator`) and prints one
// JSON line per file: {"file", "errors", "warnings", "infos", "messages", "renamed"}.
// gltf-validator 2.0.0-dev.3.10 (the newest on npm) predates KHR_gaussian_splatting and
// reports each of its `KHR_gaussian_splatting:*` attribute semantics as
// MESH_PRIMITIVE_INVALID_ATTRIBUTE; "renamed" is the report of the same file with those
// semantics renamed to application-specific ones (`_KHR_GS_*`), every accessor and byte kept,
// so that everything else the validator checks is checked.
// Usage: node validate_gltf.mjs FILE.glb…   (exit 0; the caller judges the counts)
import { readFileSync } from "node:fs";
import validator from "gltf-validator";

function summary(report) {
  const issues = report.issues;
  return {
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    messages: issues.messages
      .filter((m) => m.severity <= 1)
      .slice(0, 50)
      .map((m) => ({ code: m.code, severity: m.severity, pointer: m.pointer, message: m.message })),
  };
}

/** The GLB `bytes` with its JSON chunk rewritten by `edit`. */
function rewriteJson(bytes, edit) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const jsonLength = view.getUint32(12, true);
  const json = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLength)));
  edit(json);
  let text = new TextEncoder().encode(JSON.stringify(json));
  const padded = new Uint8Array((text.length + 3) & ~3).fill(0x20);
  padded.set(text);
  const rest = bytes.subarray(20 + jsonLength);
  const out = new Uint8Array(20 + padded.length + rest.length);
  const ov = new DataView(out.buffer);
  out.set(bytes.subarray(0, 12));
  ov.setUint32(8, out.length, true);
  ov.setUint32(12, padded.length, true);
  ov.setUint32(16, view.getUint32(16, true), true);
  out.set(padded, 20);
  out.set(rest, 20 + padded.length);
  return out;
}

const options = (uri) => ({
  uri,
  maxIssues: 10000,
  externalResourceFunction: () => Promise.reject(new Error("no external resources")),
});

for (const file of process.argv.slice(2)) {
  const bytes = new Uint8Array(readFileSync(file));
  const raw = summary(await validator.validateBytes(bytes, options(file)));
  const renamed = rewriteJson(bytes, (json) => {
    for (const mesh of json.meshes ?? []) {
      for (const prim of mesh.primitives ?? []) {
        const attrs = {};
        for (const [k, v] of Object.entries(prim.attributes)) {
          attrs[k.replace(/^KHR_gaussian_splatting:/, "_KHR_GS_")] = v;
        }
        prim.attributes = attrs;
      }
    }
  });
  const other = summary(await validator.validateBytes(renamed, options(file)));
  console.log(JSON.stringify({ file, ...raw, renamed: other }));
}
