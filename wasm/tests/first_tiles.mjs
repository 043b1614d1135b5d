// What a tile costs the browser's decoder the first time its chunks are read, and again:
// random tiles at the asset's native zoom (and the zooms just above), each opened afresh so
// that its chunks are decoded for it. Prints a Markdown table.
//
//   node wasm/tests/first_tiles.mjs WEB_DIR SIZE COUNT URL [URL...]
//
// WEB_DIR: wasm/build.sh's output; SIZE: tile pixels (256, MapLibre's default for raster-dem
// sources, or 512); URL: an asset served with Range support (nginx).
import { readFileSync } from 'node:fs';
import { resolve } from 'node:path';
import { pathToFileURL } from 'node:url';

const [web, size, count, ...urls] = process.argv.slice(2);
const { loadDecoder, RemoteAsset } = await import(pathToFileURL(`${resolve(web)}/reader.js`));
await loadDecoder(readFileSync(`${resolve(web)}/pkg/fractile_wasm_bg.wasm`));

// A deterministic generator, so that runs draw the same tiles.
let seed = 7;
const unit = () => {
  seed = (seed * 1103515245 + 12345) % 2147483648;
  return seed / 2147483648;
};
const tileX = (lon, z) => Math.floor(((lon + 180) / 360) * 2 ** z);
const tileY = (lat, z) => {
  const r = (lat * Math.PI) / 180;
  return Math.floor(((1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2) * 2 ** z);
};
const pct = (v, p) => [...v].sort((a, b) => a - b)[Math.min(v.length - 1, Math.floor(p * v.length))];

console.log('| asset | tile | zoom | tiles | first: p50 / p90 / max ms | again: p50 / max ms |');
console.log('|---|---|---|---|---|---|');
for (const url of urls) {
  const probe = await RemoteAsset.open(url);
  const [w, s, e, n] = probe.bounds;
  const native = probe.nativeZoom + Math.round(Math.log2(256 / Number(size)));
  for (const zoom of [native, native - 1, native - 2]) {
    seed = 7;
    const first = [];
    const again = [];
    for (let k = 0; k < Number(count); k++) {
      const lon = w + (e - w) * (0.1 + 0.8 * unit());
      const lat = s + (n - s) * (0.1 + 0.8 * unit());
      const a = await RemoteAsset.open(url);
      const [x, y] = [tileX(lon, zoom), tileY(lat, zoom)];
      await a.tileHeights(zoom, x, y, Number(size));
      first.push(a.lastDecodeMs);
      await a.tileHeights(zoom, x, y, Number(size));
      again.push(a.lastDecodeMs);
    }
    const f = (v) => v.toFixed(0);
    console.log(`| ${url.split('/').pop()} | ${size} px | ${zoom} | ${count} | ${f(pct(first, 0.5))} / ${f(pct(first, 0.9))} / ${f(Math.max(...first))} | ${f(pct(again, 0.5))} / ${f(Math.max(...again))} |`);
  }
}
