// A MapLibre protocol that reads fractile assets from static storage, no tile server needed:
//
//   import { addFractileProtocol } from './fractile-protocol.js';
//   const fractile = addFractileProtocol(maplibregl);
//   map.addSource('dem', { type: 'raster-dem', url: 'fractile://https://host/path/dem.fra',
//                          encoding: 'mapbox', tileSize: 256 });
//
// `fractile://<url>` answers the TileJSON the asset implies (bounds, zooms to 4 past the
// source's, as the server's); `fractile://<url>/{z}/{x}/{y}` a terrain-RGB tile decoded in a
// Web Worker (worker.js) from the byte ranges the tile needs, fetched once and kept.

const TILE = /^fractile:\/\/(.+)\/(\d+)\/(\d+)\/(\d+)(?:\.png)?$/;

/** Registers `fractile://` with `maplibregl`; returns `{ stats, tilejson, heights, close }`. */
export function addFractileProtocol(maplibregl, { encoding = 'terrainrgb', tileSize = 256, worker } = {}) {
  const w = worker || new Worker(new URL('./worker.js', import.meta.url), { type: 'module' });
  const pending = new Map();
  let next = 0;
  const stats = { tiles: 0, errors: 0, bytesFetched: 0, requests: 0, decodeMs: [] };
  w.onmessage = ({ data }) => {
    const p = pending.get(data.id);
    pending.delete(data.id);
    if (!p) return;
    if (data.error) {
      stats.errors += 1;
      p.reject(new Error(data.error));
    } else {
      p.resolve(data);
    }
  };
  const call = (message) => new Promise((resolve, reject) => {
    const id = (next += 1);
    pending.set(id, { resolve, reject });
    w.postMessage(Object.assign({ id }, message));
  });
  const note = (r) => {
    stats.bytesFetched = Math.max(stats.bytesFetched, r.bytesFetched);
    stats.requests = Math.max(stats.requests, r.requests);
    stats.decodeMs.push(r.decodeMs);
  };

  // The TileJSON an asset implies, as the server's: its bounds, zooms to 4 past the source's.
  const tilejson = async (url) => {
    const r = await call({ kind: 'meta', url });
    return {
      tilejson: '3.0.0',
      tiles: [`fractile://${url}/{z}/{x}/{y}`],
      bounds: r.bounds,
      minzoom: 0,
      maxzoom: Math.min(r.nativeZoom + 4, 22),
      nativeZoom: r.nativeZoom,
      tileSize,
      encoding: encoding === 'terrarium' ? 'terrarium' : 'mapbox',
    };
  };

  maplibregl.addProtocol('fractile', async (params) => {
    const m = params.url.match(TILE);
    if (!m) return { data: await tilejson(params.url.slice('fractile://'.length)) };
    const [, url, z, x, y] = m;
    const r = await call({ kind: 'rgba', url, z: +z, x: +x, y: +y, size: tileSize, encoding });
    stats.tiles += 1;
    note(r);
    return { data: r.bitmap };
  });

  return {
    stats,
    /** The TileJSON of the asset at `url` (a plain URL, no `fractile://`). */
    tilejson,
    /** Tile z/x/y's heights as the worker decodes them (Float32Array), with its bound. */
    async heights(url, z, x, y, size = tileSize) {
      const r = await call({ kind: 'heights', url, z, x, y, size });
      note(r);
      return r;
    },
    close() {
      maplibregl.removeProtocol('fractile');
      w.terminate();
    },
  };
}
