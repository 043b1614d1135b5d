// A map session's tiles decoded in Node from an asset read by range (wasm/js/reader.js):
// prints JSON with the bytes and requests it fetched (the opening included) and each tile's
// decode time. For tools/static_bytes.py, which runs the same tiles against a PMTiles pyramid.
//
//   node wasm/tests/session.mjs WEB_DIR ASSET_URL SIZE 'z/x/y,z/x/y,...'
import { readFileSync } from 'node:fs';
import { resolve } from 'node:path';
import { pathToFileURL } from 'node:url';

const [web, url, size, list] = process.argv.slice(2);
const { loadDecoder, RemoteAsset } = await import(pathToFileURL(`${resolve(web)}/reader.js`));
await loadDecoder(readFileSync(`${resolve(web)}/pkg/fractile_wasm_bg.wasm`));
const a = await RemoteAsset.open(url);
const opening = a.bytesFetched;
const tiles = [];
for (const t of list.split(',')) {
  const [z, x, y] = t.split('/').map(Number);
  const h = await a.tileHeights(z, x, y, Number(size));
  tiles.push({ tile: t, decodeMs: a.lastDecodeMs, valid: h.filter((v) => !Number.isNaN(v)).length });
}
console.log(JSON.stringify({ opening, bytesFetched: a.bytesFetched, requests: a.requests, nativeZoom: a.nativeZoom, tiles }));
