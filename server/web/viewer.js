// The fractile demo viewer: a DEM as 3D terrain with hillshade, an image zoomable past its native
// resolution, an iterations slider (progressive refinement) and point heights on click.
// #status records tile loads and errors, for the headless browser test.
(function () {
  const status = document.getElementById('status');
  const bump = (key) => { status.dataset[key] = String(Number(status.dataset[key]) + 1); };
  const fail = (what) => { bump('errors'); status.textContent = 'error: ' + what; };
  window.addEventListener('error', (e) => fail(e.message));
  window.addEventListener('unhandledrejection', (e) => fail(String(e.reason)));
  const consoleError = console.error;
  console.error = function (...args) { fail(args.join(' ')); consoleError.apply(console, args); };

  const origin = window.location.origin;
  const params = new URLSearchParams(window.location.search);
  const dem = params.get('dem') || 'jacksboro';
  const picture = params.get('image') || 'camera';
  const coastline = params.get('curve') || 'coast';
  const volume = params.get('volume') || 'fandisk';
  // `?near` puts the volume's camera close: the browser test's second look, which must fetch
  // deeper tiles than the first.
  const near = params.has('near');
  const withIterations = (url, n) => n === 'auto' ? url : url + (url.includes('?') ? '&' : '?') + 'iterations=' + n;
  const demTiles = (n) => [withIterations(`${origin}/v1/assets/${dem}/tiles/{z}/{x}/{y}.png?encoding=terrainrgb`, n)];
  const imageTiles = (n) => [withIterations(`${origin}/v1/assets/${picture}/tiles/{z}/{x}/{y}.png`, n)];

  const json = (r) => {
    if (!r.ok) throw new Error(`${r.url}: HTTP ${r.status}`);
    return r.json();
  };
  // The curve asset: one level per zoom step, the input's finest level where a vertex
  // spacing of ~0.1° (the 1:50m coastlines) is about 4 px (zoom 6), coarser out, finer in
  // (past the source, the details continue self-similarly).
  // The map is made once the first level has arrived, with the curve in its style: its first
  // 'idle' then means the curve is drawn, not only that an empty map is. Its request goes out
  // first, before the other maps' tiles take the browser's connections to the server.
  const coastZoom = 4;
  let coastFinest = null;
  let coastShown = null;
  const coastLevel = (zoom) => {
    const finest = coastFinest === null ? 7 : coastFinest;
    return Math.max(0, Math.min(finest + 3, finest + Math.round(zoom - 6)));
  };
  const curveAt = (level) => fetch(`${origin}/v1/assets/${coastline}/curve?level=${level}`).then(json).then((doc) => {
    coastFinest = doc.fractile.finest_level;
    coastShown = level;
    const points = doc.features.reduce((n, f) => n + f.geometry.coordinates.length, 0);
    status.dataset.coastPoints = String(points);
    status.dataset.coastLevel = String(level);
    const bound = doc.fractile.error_bound;
    document.getElementById('coast-level').textContent =
      `(level ${level} of ${doc.fractile.finest_level}, ${points} points` +
      (bound === null ? ')' : `, within ${(bound * 111.195).toFixed(1)} km)`);
    return doc;
  });
  const coastMap = curveAt(coastLevel(coastZoom)).then((doc) => {
    const coast = new maplibregl.Map({
      container: 'coast',
      style: {
        version: 8,
        sources: { coast: { type: 'geojson', data: doc } },
        layers: [
          { id: 'sea', type: 'background', paint: { 'background-color': '#cfe3f0' } },
          { id: 'coast', type: 'line', source: 'coast', paint: { 'line-color': '#20252b', 'line-width': 1.2 } },
        ],
      },
      center: [-3, 54],
      zoom: coastZoom,
      renderWorldCopies: false,
    });
    coast.on('error', (e) => fail(e.error ? e.error.message : 'map error'));
    const redraw = () => {
      const level = coastLevel(coast.getZoom());
      if (level === coastShown) return;
      coastShown = level;
      curveAt(level).then((doc) => {
        coast.getSource('coast').setData(doc);
        redraw();
      }).catch((e) => fail(String(e)));
    };
    coast.once('load', redraw);
    coast.on('zoomend', redraw);
    return coast;
  });
  coastMap.catch((e) => fail(String(e)));

  // The globe: CesiumJS, when the server has a build of it (`fractile serve --cesium DIR`), on
  // our Cesium terrain (layer.json and quantized-mesh tiles), coloured by contour lines since
  // there is no imagery. #status says 'absent', 'loading' or 'ready' (every tile in view
  // loaded), and how many terrain tiles Cesium took.
  const note = (text) => { document.getElementById('globe-note').textContent = text; };
  const startGlobe = async () => {
    status.dataset.globe = 'loading';
    // Vertex normals (our tiles' octvertexnormals extension) for the sun's shading.
    const terrain = await Cesium.CesiumTerrainProvider.fromUrl(`${origin}/v1/assets/${dem}/`, {
      requestVertexNormals: true,
    });
    const widget = new Cesium.CesiumWidget('globe', {
      terrainProvider: terrain,
      baseLayer: false,
      skyBox: false,
      skyAtmosphere: false,
      // Kept after each frame, so that a screenshot (the browser test's) shows what was drawn.
      contextOptions: { webgl: { preserveDrawingBuffer: true } },
    });
    const globe = widget.scene.globe;
    // Shaded by our tiles' vertex normals under the sun of a fixed summer morning over the DEM
    // (low, from the east-north-east, so the relief shows), not of the clock's time: the view
    // looks the same whenever it is opened (at night it would be black).
    globe.enableLighting = true;
    widget.clock.shouldAnimate = false;
    widget.clock.currentTime = Cesium.JulianDate.fromIso8601('2026-06-21T13:00:00Z');
    globe.baseColor = Cesium.Color.fromCssColorString('#a9c08f');
    globe.material = Cesium.Material.fromType('ElevationContour', {
      width: 2.0,
      spacing: 60.0,
      color: Cesium.Color.fromCssColorString('#6b4423'),
    });
    widget.camera.setView({
      destination: Cesium.Cartesian3.fromDegrees(-84.25, 36.40, 9000),
      orientation: { heading: 0, pitch: Cesium.Math.toRadians(-35), roll: 0 },
    });
    terrain.errorEvent.addEventListener((e) => fail(`terrain: ${e.message}`));
    let asked = 0;
    globe.tileLoadProgressEvent.addEventListener((queued) => {
      asked = Math.max(asked, queued);
      status.dataset.globeTiles = String(Number(status.dataset.globeTiles) + (queued > 0 ? 1 : 0));
    });
    widget.scene.postRender.addEventListener(() => {
      if (globe.tilesLoaded && asked > 0 && status.dataset.globe !== 'ready') {
        status.dataset.globe = 'ready';
        note('(loaded)');
      }
    });
  };
  // The volume: its 3D Tiles (tileset.json, implicit octree) streamed by CesiumJS in mesh
  // units, with no globe, refined where the camera looks. #status says 'absent', 'loading'
  // or 'ready' (every tile the view wants loaded) and how many tiles Cesium took.
  const startVolume = async () => {
    status.dataset.volume = 'loading';
    const widget = new Cesium.CesiumWidget('volume', {
      globe: false,
      baseLayer: false,
      skyBox: false,
      skyAtmosphere: false,
      contextOptions: { webgl: { preserveDrawingBuffer: true } },
    });
    const scene = widget.scene;
    scene.backgroundColor = Cesium.Color.fromCssColorString('#dfe6ee');
    // A fixed light from over the viewer's shoulder: the same picture at any time of day.
    scene.light = new Cesium.DirectionalLight({ direction: new Cesium.Cartesian3(-0.4, 0.6, -0.7) });
    const tileset = await Cesium.Cesium3DTileset.fromUrl(`${origin}/v1/assets/${volume}/tileset.json`);
    // A colour of its own: untextured white under the light is hard to tell from the sky.
    tileset.style = new Cesium.Cesium3DTileStyle({ color: "color('#c08a4a')" });
    scene.primitives.add(tileset);
    let loaded = 0;
    tileset.tileLoad.addEventListener(() => {
      loaded += 1;
      status.dataset.volumeTiles = String(loaded);
    });
    tileset.tileFailed.addEventListener((e) => fail(`volume tile ${e.url}: ${e.message}`));
    const sphere = tileset.boundingSphere;
    widget.camera.viewBoundingSphere(sphere,
      new Cesium.HeadingPitchRange(0.6, -0.5, sphere.radius * (near ? 1.3 : 5.0)));
    widget.camera.lookAtTransform(Cesium.Matrix4.IDENTITY);
    tileset.allTilesLoaded.addEventListener(() => {
      if (loaded > 0) {
        status.dataset.volume = 'ready';
      }
    });
  };
  fetch(`${origin}/vendor/cesium/Cesium.js`, { method: 'HEAD' }).then((r) => {
    if (!r.ok) {
      status.dataset.globe = 'absent';
      status.dataset.volume = 'absent';
      note('needs CesiumJS on the server: tools/fetch-cesium.sh, then fractile serve --cesium target/cesium/Cesium');
      return;
    }
    window.CESIUM_BASE_URL = `${origin}/vendor/cesium/`;
    const css = document.createElement('link');
    css.rel = 'stylesheet';
    css.href = `${origin}/vendor/cesium/Widgets/widgets.css`;
    document.head.appendChild(css);
    const script = document.createElement('script');
    script.src = `${origin}/vendor/cesium/Cesium.js`;
    script.onload = () => {
      startGlobe().catch((e) => fail(`globe: ${e}`));
      startVolume().catch((e) => fail(`volume: ${e}`));
    };
    script.onerror = () => fail('CesiumJS did not load');
    document.head.appendChild(script);
  }).catch((e) => fail(String(e)));

  // Both assets must exist: a missing one is an error on the page, not an empty map.
  fetch(`${origin}/v1/assets/${picture}`).then(json).catch((e) => fail(String(e)));
  fetch(`${origin}/v1/assets/${dem}`).then(json).then((meta) => {
    const [w, s, e, n] = meta.bounds || [-180, -85, 180, 85];
    const terrain = new maplibregl.Map({
      container: 'terrain',
      style: {
        version: 8,
        sources: {
          dem: { type: 'raster-dem', tiles: demTiles('auto'), tileSize: 256, encoding: 'mapbox', bounds: [w, s, e, n], maxzoom: 15 },
          relief: { type: 'raster', tiles: [`${origin}/v1/assets/${dem}/tiles/{z}/{x}/{y}.png?colormap=terrain`], tileSize: 256, bounds: [w, s, e, n], maxzoom: 15 },
        },
        layers: [
          { id: 'background', type: 'background', paint: { 'background-color': '#dde4ea' } },
          { id: 'relief', type: 'raster', source: 'relief' },
          { id: 'hillshade', type: 'hillshade', source: 'dem', paint: { 'hillshade-exaggeration': 0.5 } },
        ],
        terrain: { source: 'dem', exaggeration: 1.5 },
      },
      bounds: [w, s, e, n],
      pitch: 55,
      maxPitch: 80,
    });
    const image = new maplibregl.Map({
      container: 'image',
      style: {
        version: 8,
        sources: { img: { type: 'raster', tiles: imageTiles('auto'), tileSize: 256, maxzoom: 12 } },
        layers: [{ id: 'img', type: 'raster', source: 'img' }],
      },
      center: [0, 0],
      zoom: 1,
      renderWorldCopies: false,
    });
    for (const [name, map] of [['terrainTiles', terrain], ['imageTiles', image]]) {
      map.on('error', (e) => fail(e.error ? e.error.message : 'map error'));
      map.on('data', (e) => {
        if (e.dataType === 'source' && e.tile) {
          bump('tiles');
          bump(name);
        }
      });
    }
    const maps = [Promise.resolve(terrain), Promise.resolve(image), coastMap];
    Promise.all(maps.map((m) => m.then((map) => new Promise((ok) => map.once('idle', ok))))).then(() => {
      status.dataset.loaded = 'true';
    });

    // Decode in the browser: the same DEM read by range from /v1/assets/{dem}/file and decoded
    // by fractile's WebAssembly decoder in a Web Worker (when the server has it: `fractile
    // serve --wasm DIR`), in a panel beside the server's tiles, on the same camera. #status's
    // data-browser says 'absent', 'off', 'loading' or 'ready'.
    const toggle = document.getElementById('browser-decode');
    const panel = document.getElementById('browser');
    let browserMap = null;
    const relayout = () => { terrain.resize(); image.resize(); coastMap.then((m) => m.resize()); };
    const follow = () => {
      if (browserMap) browserMap.jumpTo({ center: terrain.getCenter(), zoom: terrain.getZoom(), bearing: terrain.getBearing(), pitch: terrain.getPitch() });
    };
    const startBrowser = async () => {
      status.dataset.browser = 'loading';
      panel.hidden = false;
      relayout();
      const { addFractileProtocol } = await import(`${origin}/wasm/fractile-protocol.js`);
      window.fractileProtocol = window.fractileProtocol || addFractileProtocol(maplibregl);
      const url = `fractile://${origin}/v1/assets/${dem}/file`;
      browserMap = new maplibregl.Map({
        container: 'browser',
        style: {
          version: 8,
          sources: {
            dem: { type: 'raster-dem', url, tileSize: 256, encoding: 'mapbox' },
            shade: { type: 'raster-dem', url, tileSize: 256, encoding: 'mapbox' },
          },
          layers: [
            { id: 'background', type: 'background', paint: { 'background-color': '#dde4ea' } },
            { id: 'hillshade', type: 'hillshade', source: 'shade', paint: { 'hillshade-exaggeration': 0.5 } },
          ],
          terrain: { source: 'dem', exaggeration: 1.5 },
        },
        center: terrain.getCenter(),
        zoom: terrain.getZoom(),
        pitch: terrain.getPitch(),
        maxPitch: 80,
        interactive: false,
      });
      browserMap.on('error', (e) => fail(e.error ? e.error.message : 'map error'));
      browserMap.on('data', (e) => { if (e.dataType === 'source' && e.tile) bump('browserTiles'); });
      browserMap.once('idle', () => {
        status.dataset.browser = 'ready';
        const s = window.fractileProtocol.stats;
        document.getElementById('browser-note').textContent = `(${s.tiles} tiles, ${s.bytesFetched} bytes fetched)`;
      });
    };
    const stopBrowser = () => {
      if (browserMap) browserMap.remove();
      browserMap = null;
      panel.hidden = true;
      status.dataset.browser = 'off';
      relayout();
    };
    terrain.on('move', follow);
    fetch(`${origin}/wasm/fractile-protocol.js`, { method: 'HEAD' }).then((r) => {
      if (!r.ok) {
        status.dataset.browser = 'absent';
        return;
      }
      toggle.disabled = false;
      toggle.addEventListener('change', () => (toggle.checked ? startBrowser().catch((e) => fail(`browser decoder: ${e}`)) : stopBrowser()));
      if (params.get('decode') === 'browser') {
        toggle.checked = true;
        startBrowser().catch((e) => fail(`browser decoder: ${e}`));
      }
    }).catch((e) => fail(String(e)));

    const slider = document.getElementById('iterations');
    const label = document.getElementById('iterations-value');
    slider.addEventListener('input', () => {
      const n = slider.value === slider.max ? 'auto' : slider.value;
      label.textContent = n;
      terrain.getSource('dem').setTiles(demTiles(n));
      image.getSource('img').setTiles(imageTiles(n));
    });

    terrain.on('click', (e) => {
      const { lng, lat } = e.lngLat;
      fetch(`${origin}/v1/assets/${dem}/point/${lng},${lat}`).then((r) => r.json()).then((p) => {
        const out = document.getElementById('point');
        if (p.values && p.values[0] !== null) {
          // The bound against the source data where the asset has one (format 5), else only
          // how far the iterations are from the fractal's own limit.
          const bound = p.error_bound !== null
            ? `± ${p.error_bound.toFixed(1)} of the source`
            : `± ${p.convergence_bound.toFixed(2)} of the fractal (no source bound in this asset)`;
          out.textContent = `${lng.toFixed(4)}, ${lat.toFixed(4)}: ${p.values[0].toFixed(1)} ${meta.units || ''} ${bound} (${p.iterations} steps)`;
        } else {
          out.textContent = p.detail || 'no data here';
        }
      });
    });
  }).catch((e) => fail(String(e)));
})();
