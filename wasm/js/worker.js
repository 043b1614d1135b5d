// The Web Worker that decodes tiles off the page's thread (fractile-protocol.js posts to it):
// one RemoteAsset per URL, tiles answered as ImageBitmaps of terrain-RGB (or Terrarium) pixels.
import { loadDecoder, RemoteAsset } from './reader.js';

const assets = new Map();
// The opened ones, to tell an asset whose decoder failed (`broken`): it is opened again.
const opened = new Map();

function asset(url) {
  if (opened.get(url)?.broken) {
    opened.delete(url);
    assets.delete(url);
  }
  if (!assets.has(url)) {
    const a = RemoteAsset.open(url);
    a.then((o) => opened.set(url, o), () => assets.delete(url));
    assets.set(url, a);
  }
  return assets.get(url);
}

self.onmessage = async ({ data }) => {
  const { id, kind, url } = data;
  try {
    await loadDecoder();
    const a = await asset(url);
    if (kind === 'meta') {
      self.postMessage({ id, meta: a.meta, bounds: a.bounds, nativeZoom: a.nativeZoom });
      return;
    }
    const { z, x, y, size, encoding } = data;
    let out;
    if (kind === 'heights') {
      const heights = await a.tileHeights(z, x, y, size);
      out = { id, heights, bound: a.bound };
      self.postMessage(Object.assign(out, stats(a)), [heights.buffer]);
      return;
    }
    const rgba = await a.tileRgba(z, x, y, size, encoding);
    const bitmap = await createImageBitmap(new ImageData(new Uint8ClampedArray(rgba.buffer), size, size));
    out = { id, bitmap, bound: a.bound };
    self.postMessage(Object.assign(out, stats(a)), [bitmap]);
  } catch (e) {
    self.postMessage({ id, error: String(e && e.message ? e.message : e) });
  }
};

function stats(a) {
  return { decodeMs: a.lastDecodeMs, bytesFetched: a.bytesFetched, requests: a.requests };
}
