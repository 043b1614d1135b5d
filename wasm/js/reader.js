// An asset file on static storage (S3, a CDN, nginx) read by HTTP range requests and decoded by
// fractile's WebAssembly module: a tile fetches only the chunks it reads, all at once, each
// once. Works in a Web Worker, a page or Node (>= 18, fetch built in).
//
//   await loadDecoder();                       // once (Node: loadDecoder(wasmBytes))
//   const a = await RemoteAsset.open(url);     // header and chunk table (one request)
//   const h = await a.tileHeights(z, x, y);    // Float32Array, NaN where there is no data
import init, { FractileReader, initSync } from './pkg/fractile_wasm.js';

let ready = null;

/** Loads the WebAssembly module once: from beside this file, or from `wasm` (bytes or a URL). */
export function loadDecoder(wasm) {
  if (!ready) {
    ready = wasm instanceof Uint8Array || wasm instanceof ArrayBuffer
      ? Promise.resolve(initSync({ module: wasm }))
      : init(wasm ? { module_or_path: wasm } : undefined);
  }
  return ready;
}

/** The first bytes read on opening: a chunked file's header and table, or a small file whole. */
const OPENING_BYTES = 16 << 10;

/** `length` bytes of `url` from `offset`, and the file's length (from Content-Range). */
async function fetchRange(fetchFn, url, offset, length) {
  const r = await fetchFn(url, { headers: { Range: `bytes=${offset}-${offset + length - 1}` } });
  if (r.status === 200) {
    // No range support: the whole file came; keep what was asked of it.
    const all = new Uint8Array(await r.arrayBuffer());
    return { bytes: all.subarray(offset, offset + length), total: all.length, whole: all };
  }
  if (r.status !== 206) throw new Error(`${url}: HTTP ${r.status} for bytes ${offset}+${length}`);
  const total = Number((r.headers.get('Content-Range') || '').split('/')[1]);
  return { bytes: new Uint8Array(await r.arrayBuffer()), total };
}

export class RemoteAsset {
  constructor(url, reader, fetchFn) {
    this.url = url;
    this.reader = reader;
    this.fetchFn = fetchFn;
    /** Bytes and requests this asset has fetched. */
    this.bytesFetched = 0;
    this.requests = 0;
    /** Milliseconds the last tile took to decode, its bytes in hand. */
    this.lastDecodeMs = 0;
    this.inflight = new Map();
  }

  /** Opens `url`: its header and chunk table (a small file: all of it). */
  static async open(url, { cacheBytes = 256 << 20, fetch: fetchFn = globalThis.fetch.bind(globalThis) } = {}) {
    const first = await fetchRange(fetchFn, url, 0, OPENING_BYTES);
    if (!(first.total > 0)) throw new Error(`${url}: no Content-Range length`);
    const a = new RemoteAsset(url, new FractileReader(first.total, cacheBytes), fetchFn);
    a.requests = 1;
    a.bytesFetched = first.bytes.length;
    a.reader.add(0, first.whole || first.bytes);
    a.meta = JSON.parse(await a.retry(() => a.reader.open()));
    const [w, s, e, n, nativeZoom] = a.reader.mapFrame(256);
    a.bounds = [w, s, e, n];
    a.nativeZoom = nativeZoom;
    return a;
  }

  /** Fetches bytes `offset..offset+length` once (concurrent asks share one request). */
  fetchBytes(offset, length) {
    const key = `${offset}+${length}`;
    if (!this.inflight.has(key)) {
      const p = fetchRange(this.fetchFn, this.url, offset, length).then(({ bytes }) => {
        this.requests += 1;
        this.bytesFetched += bytes.length;
        this.reader.add(offset, bytes);
      });
      p.finally(() => this.inflight.delete(key)).catch(() => {});
      this.inflight.set(key, p);
    }
    return this.inflight.get(key);
  }

  /** Runs `call` until it no longer lacks bytes, fetching what it names each time. */
  async retry(call) {
    for (let i = 0; i < 64; i += 1) {
      try {
        return call();
      } catch (e) {
        const m = this.reader.missing();
        if (!m) throw e;
        await this.fetchBytes(m[0], m[1]);
      }
    }
    throw new Error(`${this.url}: still lacking bytes after 64 fetches`);
  }

  /** Fetches every chunk tile z/x/y reads, in parallel. */
  async prefetchTile(z, x, y, size) {
    const r = this.reader.tileRanges(z, x, y, size);
    const wanted = [];
    for (let i = 0; i < r.length; i += 2) wanted.push(this.fetchBytes(r[i], r[i + 1]));
    await Promise.all(wanted);
  }

  /** Tile z/x/y as size x size heights (NaN: no data), as the server answers it. */
  async tileHeights(z, x, y, size = 256) {
    await this.prefetchTile(z, x, y, size);
    return this.retry(() => this.timed(() => this.reader.tile(z, x, y, size)));
  }

  /** Tile z/x/y as RGBA pixels for a `raster-dem` source (`terrainrgb` or `terrarium`). */
  async tileRgba(z, x, y, size = 256, encoding = 'terrainrgb') {
    await this.prefetchTile(z, x, y, size);
    return this.retry(() => this.timed(() => this.reader.tileRgba(z, x, y, size, encoding)));
  }

  /** The bound of the last tile's heights (source units). */
  get bound() {
    return this.reader.bound();
  }

  /** `{ values, errorBound }` at (lon, lat). */
  async point(lon, lat) {
    const v = await this.retry(() => this.reader.point(lon, lat));
    return { values: Array.from(v.subarray(0, v.length - 1)), errorBound: v[v.length - 1] };
  }

  timed(call) {
    const t0 = performance.now();
    const out = call();
    this.lastDecodeMs = performance.now() - t0;
    return out;
  }
}
