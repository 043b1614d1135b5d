// The browser's decoder against the server, in Node: each asset is read by range from a static
// file server (nginx) through wasm/js/reader.js, 20 tiles at zooms inside and past the source
// are decoded in WebAssembly and compared with the server's float32 tiles of the same asset
// (`.f32`: no PNG rounding on either side). Prints a table; exits 1 on any difference beyond
// `--tolerance` (default 0.05, half a step of terrain-RGB), or on NaN (nodata) where the other
// has a height.
//
//   node wasm/tests/parity.mjs --web target/wasm-web --static http://127.0.0.1:P/ \
//        --server http://127.0.0.1:Q --assets jacksboro,etopo20 [--tiles 20]
import { readFileSync } from 'node:fs';
import { resolve } from 'node:path';
import { pathToFileURL } from 'node:url';

const args = Object.fromEntries(
  process.argv.slice(2).reduce((acc, a, i, all) => (a.startsWith('--') ? [...acc, [a.slice(2), all[i + 1]]] : acc), []),
);
const web = resolve(args.web || 'target/wasm-web');
const { loadDecoder, RemoteAsset } = await import(pathToFileURL(`${web}/reader.js`));
await loadDecoder(readFileSync(`${web}/pkg/fractile_wasm_bg.wasm`));
const tolerance = Number(args.tolerance || 0.05);
const ids = args.assets.split(',');
const wanted = Number(args.tiles || 20);

/** The XYZ tile holding (lon, lat) at zoom z. */
function tileOf(lon, lat, z) {
  const n = 2 ** z;
  const r = (Math.max(-85.05, Math.min(85.05, lat)) * Math.PI) / 180;
  const x = Math.floor(((lon + 180) / 360) * n);
  const y = Math.floor(((1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2) * n);
  return [Math.min(n - 1, Math.max(0, x)), Math.min(n - 1, Math.max(0, y))];
}

const rows = [];
let failed = 0;
const perAsset = Math.ceil(wanted / ids.length);
for (const id of ids) {
  // --static: a folder URL holding ID.fra, or a template with {id} (the server's own
  // /v1/assets/{id}/file, which answers ranges too).
  const at = args.static.includes('{id}') ? args.static.replace('{id}', id) : new URL(`${id}.fra`, args.static).href;
  const a = await RemoteAsset.open(at);
  const [w, s, e, n] = a.bounds;
  // Zooms from two under the native one to three past it; at each, a tile at the centre and
  // one at a quarter of the extent (different chunks).
  const tiles = [];
  for (let z = Math.max(0, a.nativeZoom - 2); tiles.length < perAsset; z += 1) {
    for (const [fx, fy] of [[0.5, 0.5], [0.27, 0.71]]) {
      const [x, y] = tileOf(w + fx * (e - w), s + fy * (n - s), z);
      if (!tiles.some(([tz, tx, ty]) => tz === z && tx === x && ty === y)) tiles.push([z, x, y]);
    }
  }
  for (const [z, x, y] of tiles.slice(0, perAsset)) {
    const before = a.bytesFetched;
    const ours = await a.tileHeights(z, x, y, 256);
    const r = await fetch(`${args.server}/v1/assets/${id}/tiles/${z}/${x}/${y}.f32`);
    if (r.status !== 200) throw new Error(`server: HTTP ${r.status} for ${id} ${z}/${x}/${y}`);
    const theirs = new Float32Array(await r.arrayBuffer());
    let worst = 0;
    let nodataMismatch = 0;
    let valid = 0;
    for (let i = 0; i < theirs.length; i += 1) {
      const [p, q] = [ours[i], theirs[i]];
      if (Number.isNaN(p) || Number.isNaN(q)) {
        if (Number.isNaN(p) !== Number.isNaN(q)) nodataMismatch += 1;
        continue;
      }
      valid += 1;
      worst = Math.max(worst, Math.abs(p - q));
    }
    const ok = ours.length === theirs.length && worst <= tolerance && nodataMismatch === 0;
    if (!ok) failed += 1;
    rows.push({ asset: id, tile: `${z}/${x}/${y}`, past: z > a.nativeZoom, valid, worst, nodataMismatch,
      decodeMs: a.lastDecodeMs, fetched: a.bytesFetched - before, ok });
  }
  rows.push({ asset: id, tile: 'total', fetched: a.bytesFetched, requests: a.requests });
}
console.table(rows);
const compared = rows.filter((r) => r.tile !== 'total');
console.log(`${compared.length - failed} of ${compared.length} tiles equal the server's within ${tolerance}`);
if (compared.length < wanted || compared.every((r) => r.valid === 0)) {
  console.log('too few tiles with data compared');
  process.exit(1);
}
process.exit(failed ? 1 : 0);
