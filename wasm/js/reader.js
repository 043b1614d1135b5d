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

/** How long a response may send nothing (its headers, or its next bytes) before it is
 * abandoned: a server that stalls mid-body otherwise held the reader for 301 s in Node and
 * forever in a browser. */
const STALL_MS = 30000;

/** The most bytes taken from a server that ignores Range and sends the file whole. */
const MOST_WHOLE = 64 << 20;

/** The body of `r`, at most `most` bytes (more is an error, and the rest is not read), each
 * read within STALL_MS of the last. */
async function readBody(r, most, stall, url) {
  const said = Number(r.headers.get('Content-Length'));
  if (Number.isFinite(said) && said > most) {
    stall.abort();
    throw new Error(`${url}: the server sends ${said} bytes where ${most} at most were asked`);
  }
  const parts = [];
  let got = 0;
  const reader = r.body.getReader();
  for (;;) {
    stall.reset();
    const { done, value } = await reader.read();
    if (done) break;
    got += value.length;
    if (got > most) {
      stall.abort();
      throw new Error(`${url}: the server sent more than the ${most} bytes asked`);
    }
    parts.push(value);
  }
  const out = new Uint8Array(got);
  let at = 0;
  for (const p of parts) {
    out.set(p, at);
    at += p.length;
  }
  return out;
}

/** An AbortController whose timer, reset on every sign of life, aborts after STALL_MS. */
function stallTimer(url, stallMs) {
  const controller = new AbortController();
  let timer = null;
  const stall = {
    signal: controller.signal,
    timedOut: null,
    reset() {
      clearTimeout(timer);
      timer = setTimeout(() => {
        stall.timedOut = new Error(`${url}: no bytes for ${stallMs / 1000} s`);
        controller.abort(stall.timedOut);
      }, stallMs);
    },
    abort() {
      clearTimeout(timer);
      controller.abort();
    },
    done() {
      clearTimeout(timer);
    },
  };
  stall.reset();
  return stall;
}

/** `length` bytes of `url` from `offset`, and the file's length (from Content-Range). Reads no
 * more than asked: a range answer must be the range asked; a server that ignores ranges may send
 * the file whole only when it is small (MOST_WHOLE). */
async function fetchRange(fetchFn, url, offset, length, stallMs = STALL_MS) {
  const stall = stallTimer(url, stallMs);
  try {
    const r = await fetchFn(url, { headers: { Range: `bytes=${offset}-${offset + length - 1}` }, signal: stall.signal });
    if (r.status === 200) {
      // No range support: the whole file comes; keep what was asked of it.
      const all = await readBody(r, MOST_WHOLE, stall, url);
      return { bytes: all.subarray(offset, offset + length), total: all.length, whole: all };
    }
    if (r.status !== 206) {
      stall.abort();
      throw new Error(`${url}: HTTP ${r.status} for bytes ${offset}+${length}`);
    }
    const m = /^bytes (\d+)-(\d+)\/(\d+)$/.exec((r.headers.get('Content-Range') || '').trim());
    if (!m) {
      stall.abort();
      throw new Error(`${url}: a range answer without Content-Range (on another origin, the server must expose it)`);
    }
    const [first, last, total] = [Number(m[1]), Number(m[2]), Number(m[3])];
    const want = Math.min(length, Math.max(0, total - offset));
    if (first !== offset || last !== offset + want - 1) {
      stall.abort();
      throw new Error(`${url}: asked bytes ${offset}-${offset + length - 1}, the server sent ${first}-${last}`);
    }
    const bytes = await readBody(r, want, stall, url);
    if (bytes.length !== want) throw new Error(`${url}: ${bytes.length} bytes for a range of ${want}`);
    return { bytes, total };
  } catch (e) {
    throw stall.timedOut || e;
  } finally {
    stall.done();
  }
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
  static async open(url, { cacheBytes = 256 << 20, fetch: fetchFn = globalThis.fetch.bind(globalThis), stallMs = STALL_MS } = {}) {
    const first = await fetchRange(fetchFn, url, 0, OPENING_BYTES, stallMs);
    if (!(first.total > 0)) throw new Error(`${url}: no Content-Range length`);
    const a = new RemoteAsset(url, new FractileReader(first.total, cacheBytes), fetchFn);
    a.stallMs = stallMs;
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
      const p = fetchRange(this.fetchFn, this.url, offset, length, this.stallMs).then(({ bytes }) => {
        this.requests += 1;
        this.bytesFetched += bytes.length;
        this.reader.add(offset, bytes);
      });
      p.finally(() => this.inflight.delete(key)).catch(() => {});
      this.inflight.set(key, p);
    }
    return this.inflight.get(key);
  }

  /** Runs `call` until it no longer lacks bytes, fetching what it names each time. A trap of
   * the decoder (out of memory, a bug) leaves its state unknown: this asset then says so on
   * every call, and must be opened again (`broken` holds why; the worker reopens it). */
  async retry(call) {
    for (let i = 0; i < 64; i += 1) {
      if (this.broken) throw new Error(`${this.url}: the decoder failed earlier (${this.broken}); open the asset again`);
      try {
        return call();
      } catch (e) {
        if (e instanceof WebAssembly.RuntimeError) {
          this.broken = String(e.message || e);
          throw new Error(`${this.url}: the decoder failed (${this.broken}); open the asset again`);
        }
        const m = this.reader.missing();
        if (!m) throw e;
        await this.fetchBytes(m[0], m[1]);
      }
    }
    throw new Error(`${this.url}: still lacking bytes after 64 fetches`);
  }

  /** Fetches every chunk tile z/x/y reads, in parallel. */
  async prefetchTile(z, x, y, size) {
    const r = await this.retry(() => this.reader.tileRanges(z, x, y, size));
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
