// Reads a 3D Tiles tileset with the 3d-tiles-tools library (npm `3d-tiles-tools`): traverses
// every tile, resolves every content URI and identifies its data type from the bytes, and
// prints one JSON object: {"version", "geometricError", "tiles", "contents": [{"uri", "type",
// "bytes", "level"}], "maxLevel"}.
// Usage: node read_tileset.mjs DIR   (DIR holds tileset.json)
import { readFileSync } from "node:fs";
import path from "node:path";
import {
  ResourceResolvers,
  TilesetTraverser,
  BufferedContentData,
  ContentDataTypeRegistry,
} from "3d-tiles-tools";

const dir = path.resolve(process.argv[2]);
const tileset = JSON.parse(readFileSync(path.join(dir, "tileset.json"), "utf8"));
const resolver = ResourceResolvers.createFileResourceResolver(dir);
const traverser = new TilesetTraverser(dir, resolver, { depthFirst: true });
const contents = [];
let tiles = 0;
let maxLevel = 0;
await traverser.traverse(tileset, async (tile) => {
  tiles += 1;
  maxLevel = Math.max(maxLevel, tile.level);
  for (const c of tile.getFinalContents()) {
    const data = await tile.getResourceResolver().resolveData(c.uri);
    if (data === undefined) {
      throw new Error(`content ${c.uri} cannot be resolved`);
    }
    const type = await ContentDataTypeRegistry.findContentDataType(
      new BufferedContentData(c.uri, data),
    );
    contents.push({ uri: c.uri, type, bytes: data.length, level: tile.level });
  }
  return true;
});
console.log(
  JSON.stringify({
    version: tileset.asset.version,
    geometricError: tileset.geometricError,
    tiles,
    maxLevel,
    contents,
  }),
);
