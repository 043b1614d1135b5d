// The browser's reader against servers that lie or stall and files that are broken (issue 74),
// in Node over real HTTP on loopback: every case ends in an Error, never a trap or a hang; a
// tile too large is refused and the reader still answers the next; memory stays bounded.
// Prints a table of outcomes and a closing "hostile: N passed, N failed" line; exits 1 on any
// failure.
//
//   node wasm/tests/hostile.mjs --web target/wasm-web --asset etopo20.fra [--mutants 200]
import { readFileSync } from 'node:fs';
import { createServer } from 'node:http';
import { resolve } from 'node:path';
import { pathToFileURL } from 'node:url';

const args = Object.fromEntries(
  process.argv.slice(2).reduce((acc, a, i, all) => (a.startsWith('--') ? [...acc, [a.slice(2), all[i + 1]]] : acc), []),
);
const web = resolve(args.web || 'target/wasm-web');
const { loadDecoder, RemoteAsset } = await import(pathToFileURL(`${web}/reader.js`));
await loadDecoder(readFileSync(`${web}/pkg/fractile_wasm_bg.wasm`));
const asset = readFileSync(args.asset);
const mutantCount = Number(args.mutants || 200);
const STALL_MS = 1000;

/** A seeded generator (mulberry32), so that a failing mutant can be made again. */
function random(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

/** Mutant `k` of the asset: bytes flipped anywhere, bytes flipped in its header and table, cut
 * short, or a run of its table set to 0xFF (offsets and lengths far past the file). */
function mutant(k) {
  const r = random(k + 1);
  const b = Buffer.from(asset);
  const head = Math.min(b.length, 4096);
  switch (k % 4) {
    case 0:
      for (let i = 0, n = 1 + Math.floor(r() * 8); i < n; i += 1) b[Math.floor(r() * b.length)] ^= 1 << Math.floor(r() * 8);
      return b;
    case 1:
      for (let i = 0, n = 1 + Math.floor(r() * 4); i < n; i += 1) b[Math.floor(r() * head)] ^= 0xff;
      return b;
    case 2:
      return b.subarray(0, Math.floor(r() * b.length));
    default: {
      const at = 12 + Math.floor(r() * (head - 20));
      b.fill(0xff, at, at + 8);
      return b;
    }
  }
}

/** Answers a GET of `bytes` as a static host does: ranges (206), or the whole file. */
function serveBytes(req, res, bytes) {
  const m = /^bytes=(\d+)-(\d*)$/.exec(req.headers.range || '');
  if (!m) {
    res.writeHead(200, { 'Content-Length': bytes.length });
    res.end(bytes);
    return;
  }
  const first = Number(m[1]);
  const last = Math.min(m[2] === '' ? bytes.length - 1 : Number(m[2]), bytes.length - 1);
  if (first >= bytes.length || first > last) {
    res.writeHead(416, { 'Content-Range': `bytes */${bytes.length}` });
    res.end();
    return;
  }
  res.writeHead(206, { 'Content-Range': `bytes ${first}-${last}/${bytes.length}`, 'Content-Length': last - first + 1 });
  res.end(bytes.subarray(first, last + 1));
}

/** Writes zeros for as long as the reader takes them. */
function endless(res) {
  const zeros = Buffer.alloc(1 << 16);
  const more = () => {
    while (!res.destroyed && res.write(zeros));
    if (!res.destroyed) res.once('drain', more);
  };
  res.on('error', () => {});
  more();
}

const server = createServer((req, res) => {
  const path = req.url.split('?')[0];
  const range = /^bytes=(\d+)-(\d+)$/.exec(req.headers.range || '');
  if (path === '/good.fra') return serveBytes(req, res, asset);
  if (path === '/whole.fra') {
    // Ignores Range and sends a 100 GB file.
    res.writeHead(200, { 'Content-Length': String(100 * 2 ** 30) });
    return endless(res);
  }
  if (path === '/unsaid.fra') {
    // Ignores Range, says no length, and runs on.
    res.writeHead(200);
    return endless(res);
  }
  if (path === '/long.fra' && range) {
    // Says the range asked, and sends far more.
    res.writeHead(206, { 'Content-Range': `bytes ${range[1]}-${range[2]}/${asset.length}` });
    return endless(res);
  }
  if (path === '/other.fra' && range) {
    // Answers another range than the one asked.
    res.writeHead(206, { 'Content-Range': `bytes 1-${Number(range[2]) + 1}/${asset.length}` });
    return res.end(asset.subarray(1, Number(range[2]) + 2));
  }
  if (path === '/stall.fra' && range) {
    // Sends half the range, then nothing.
    const [first, last] = [Number(range[1]), Number(range[2])];
    res.writeHead(206, { 'Content-Range': `bytes ${first}-${last}/${asset.length}`, 'Content-Length': last - first + 1 });
    res.write(asset.subarray(first, first + Math.floor((last - first + 1) / 2)));
    return undefined;
  }
  const m = /^\/m(\d+)\.fra$/.exec(path);
  if (m) return serveBytes(req, res, mutant(Number(m[1])));
  res.writeHead(404);
  res.end();
  return undefined;
});
await new Promise((ok) => server.listen(0, '127.0.0.1', ok));
const base = `http://127.0.0.1:${server.address().port}`;

let passed = 0;
let failed = 0;
function check(what, ok, detail = '') {
  if (ok) passed += 1;
  else failed += 1;
  console.log(`${ok ? 'ok' : 'FAILED'}: ${what}${detail ? ` (${detail})` : ''}`);
}

/** How `promise` ends within `ms`: 'value', 'error' (an Error), 'trap' or 'hang'. */
async function outcome(promise, ms) {
  let timer;
  const hang = new Promise((ok) => { timer = setTimeout(() => ok({ kind: 'hang' }), ms); });
  const ended = promise.then(
    (value) => ({ kind: 'value', value }),
    (e) => ({ kind: e instanceof WebAssembly.RuntimeError ? 'trap' : 'error', message: String(e && e.message) }),
  );
  const r = await Promise.race([ended, hang]);
  clearTimeout(timer);
  return r;
}

// Servers that lie or stall: each open ends in an Error within seconds.
for (const [name, what] of [
  ['whole', 'ignores Range and says 100 GB'],
  ['unsaid', 'ignores Range and sends on without a length'],
  ['long', 'sends a 206 far longer than asked'],
  ['other', 'sends a 206 of another range'],
  ['stall', 'stalls mid-body'],
]) {
  const t0 = performance.now();
  const r = await outcome(RemoteAsset.open(`${base}/${name}.fra`, { stallMs: STALL_MS }), 20000);
  const ms = performance.now() - t0;
  check(`a server that ${what}: an error in ${Math.round(ms)} ms`, r.kind === 'error' && ms < 15000, r.message || r.kind);
}

// A tile too large is refused before anything is made, and the reader answers the next one.
const good = await RemoteAsset.open(`${base}/good.fra`, { stallMs: STALL_MS });
const huge = await outcome(good.tileHeights(0, 0, 0, 30000), 20000);
check('a tile of 30,000 pixels a side is refused, not a trap', huge.kind === 'error' && /pixels a side/.test(huge.message), huge.message || huge.kind);
const next = await outcome(good.tileHeights(0, 0, 0, 256), 20000);
check('the reader answers the next tile', next.kind === 'value' && next.value.length === 256 * 256 && next.value.some(Number.isFinite), next.message || next.kind);

// A trap of the module (none of the inputs above makes one; out of memory would): the asset
// says plainly that it must be opened again, on that call and every later one, and opened
// again it answers.
const victim = await RemoteAsset.open(`${base}/good.fra`, { stallMs: STALL_MS });
const trapped = await outcome(victim.retry(() => { throw new WebAssembly.RuntimeError('unreachable'); }), 5000);
const later = await outcome(victim.tileHeights(0, 0, 0, 256), 5000);
check('after a trap, the asset says it must be opened again', trapped.kind === 'error' && /open the asset again/.test(trapped.message)
  && later.kind === 'error' && /open the asset again/.test(later.message) && Boolean(victim.broken), `${trapped.message}; then ${later.message}`);
const reopened = await outcome(RemoteAsset.open(`${base}/good.fra`).then((a) => a.tileHeights(0, 0, 0, 256)), 20000);
check('opened again, it answers', reopened.kind === 'value' && reopened.value.some(Number.isFinite), reopened.message || reopened.kind);

// Broken files: each mutant opens and answers three tiles, or fails with an Error.
const counts = { value: 0, error: 0, trap: 0, hang: 0 };
const traps = [];
let rssPeak = 0;
for (let k = 0; k < mutantCount; k += 1) {
  const url = `${base}/m${k}.fra`;
  const opened = await outcome(RemoteAsset.open(url, { stallMs: STALL_MS, cacheBytes: 64 << 20 }), 20000);
  let end = opened;
  if (opened.kind === 'value') {
    const a = opened.value;
    for (const [z, x, y] of [[0, 0, 0], [a.nativeZoom, 0, 0], [Math.max(0, a.nativeZoom - 1), 1, 0]]) {
      end = await outcome(a.tileHeights(z, x, y, 256), 20000);
      if (end.kind !== 'value') break;
    }
  }
  counts[end.kind] += 1;
  if (end.kind === 'trap' || end.kind === 'hang') traps.push(`m${k}: ${end.kind} ${end.message || ''}`);
  rssPeak = Math.max(rssPeak, process.memoryUsage().rss);
}
console.log(`mutants: ${mutantCount}, answered ${counts.value}, refused ${counts.error}, trapped ${counts.trap}, hung ${counts.hang}; peak RSS ${Math.round(rssPeak / 2 ** 20)} MB`);
traps.slice(0, 10).forEach((t) => console.log(`  ${t}`));
check('no mutant traps the decoder or hangs the reader', counts.trap === 0 && counts.hang === 0);
check('some mutants are refused (the mutations reach the reader)', counts.error > mutantCount / 10);
check('memory stays under 1.5 GB', rssPeak < 1.5 * 2 ** 30, `${Math.round(rssPeak / 2 ** 20)} MB`);

server.closeAllConnections();
server.close();
console.log(`hostile: ${passed} passed, ${failed} failed`);
process.exit(failed === 0 ? 0 : 1);
