// The one helper of validate_gltf.mjs and cesium_shot.mjs: a GLB with the
// `KHR_gaussian_splatting:*` attribute semantics of its mesh primitives renamed to
// application-specific ones (`_KHR_GS_*`); every accessor and every byte of the BIN chunk kept.
// For tools that predate the extension: gltf-validator 2.0.0-dev.3.10 rejects the names, and
// CesiumJS 1.145 (which draws KHR_gaussian_splatting only with SPZ compression) turns unknown
// semantics into GLSL identifiers, where ':' does not compile.
export function renameGaussianSemantics(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const jsonLength = view.getUint32(12, true);
  const json = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLength)));
  for (const mesh of json.meshes ?? []) {
    for (const prim of mesh.primitives ?? []) {
      const attrs = {};
      for (const [k, v] of Object.entries(prim.attributes)) {
        attrs[k.replace(/^KHR_gaussian_splatting:/, "_KHR_GS_")] = v;
      }
      prim.attributes = attrs;
    }
  }
  const text = new TextEncoder().encode(JSON.stringify(json));
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
