// Re-packs an SPZ file at another format version with the SPZ library that splat-transform
// bundles (Niantic's spz, compiled to WebAssembly), without changing axes:
//   node tools/js/spz_version.mjs IN.spz OUT.spz VERSION
// The splat-format tests make their version 2 file with it (splat-transform writes 3 and 4).
import fs from 'node:fs';
import path from 'node:path';

const dist = path.join(import.meta.dirname, 'node_modules/@playcanvas/splat-transform/dist');
const index = fs.readFileSync(path.join(dist, 'index.mjs'), 'utf8');
const found = index.match(/import\('\.\/(spz-[^']+\.js)'\)/);
if (!found) {
    throw new Error('splat-transform does not import its SPZ module as expected');
}
const { default: createModule } = await import(path.join(dist, found[1]));
const spz = await createModule();
const [input, output, version] = process.argv.slice(2);
const rub = spz.CoordinateSystem.RUB;
const cloud = spz.loadSpzFromBuffer(new Uint8Array(fs.readFileSync(input)), { to: rub });
const bytes = spz.saveSpzToBuffer(cloud, {
    version: Number(version), from: rub, sh1Bits: 5, shRestBits: 4,
});
fs.writeFileSync(output, bytes);
