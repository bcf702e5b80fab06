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
import { renameGaussianSemantics } from "./glb_rename.mjs";

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

const options = (uri) => ({
  uri,
  maxIssues: 10000,
  externalResourceFunction: () => Promise.reject(new Error("no external resources")),
});

for (const file of process.argv.slice(2)) {
  const bytes = new Uint8Array(readFileSync(file));
  const raw = summary(await validator.validateBytes(bytes, options(file)));
  const renamed = renameGaussianSemantics(bytes);
  const other = summary(await validator.validateBytes(renamed, options(file)));
  console.log(JSON.stringify({ file, ...raw, renamed: other }));
}
