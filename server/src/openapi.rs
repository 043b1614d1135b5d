//! The OpenAPI 3.1 description of the HTTP API, served at `/v1/openapi.json`. Written by hand
//! (a derive crate would need annotations on every handler and type for the same result). Tests
//! keep it and the router in step both ways: every documented path is requested, and every
//! route of `api::router` must be documented; closed choices come from `fractile-proto`.

use fractile_proto::ErrorCode;
use fractile_proto::query::{
    Backend, Choice, Colormap, HeightEncoding, MeshFormat, Precision, RegionFormat,
};
use serde_json::{Value, json};

fn param(name: &str, place: &str, schema: Value, description: &str) -> Value {
    json!({"name": name, "in": place, "required": place == "path", "schema": schema, "description": description})
}

fn error_responses() -> Value {
    json!({
        "400": {"$ref": "#/components/responses/Error"},
        "404": {"$ref": "#/components/responses/Error"}
    })
}

/// A closed choice's names, from `fractile-proto` (what the handlers parse and the client writes).
fn names<C: Choice>() -> Vec<&'static str> {
    C::ALL.iter().map(|c| c.name()).collect()
}

/// The document.
pub(crate) fn document() -> Value {
    // Every error code, from the one list in `fractile-proto`.
    let codes: Vec<&str> = ErrorCode::ALL.iter().map(|c| c.as_str()).collect();
    let id = param(
        "id",
        "path",
        json!({"type": "string", "pattern": "^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"}),
        "Asset id",
    );
    let iterations = param(
        "iterations",
        "query",
        json!({"type": "integer", "minimum": 1, "maximum": 64}),
        "Most inverse steps (default: the server's limit)",
    );
    let tolerance = param(
        "tolerance",
        "query",
        json!({"type": "number", "exclusiveMinimum": 0}),
        "Error bound wanted, value units: each point stops once its own bound is under it (default for tiles, regions and meshes of a region: an eighth of the largest source error over them, which their X-Error-Bound carries anyway; for points and quantized-mesh terrain tiles, whose neighbours share edge vertices: an eighth of the asset's smallest source error; never under half a quantisation step of the source)",
    );
    let backend = param(
        "backend",
        "query",
        json!({"enum": names::<Backend>()}),
        "Where continuous decoding runs (default: the server's setting; gpu on a server without an adapter is 400 gpu_unavailable)",
    );
    let mut ok_tile = error_responses();
    ok_tile["200"] = json!({"description": "The tile", "headers": {"X-Error-Bound": {"schema": {"type": "number"}, "description": "Bound on |value - source| (the asset's measured source error over the tile plus X-Convergence-Bound), value units; absent for assets encoded before format version 5"}, "X-Convergence-Bound": {"schema": {"type": "number"}, "description": "Bound on the distance to the fractal's attractor (what more iterations shrink), value units"}, "ETag": {"schema": {"type": "string"}}}, "content": {"image/png": {}, "application/octet-stream": {}}});
    ok_tile["304"] = json!({"description": "Not modified (If-None-Match)"});
    let mut doc = json!({
        "openapi": "3.1.0",
        "info": {"title": "fractile", "version": env!("CARGO_PKG_VERSION"), "description": "Images and terrain stored as fractals, decoded on request at any resolution. Every decoded answer carries an a-priori error bound."},
        "paths": {
            "/healthz": {"get": {"summary": "Liveness", "responses": {"200": {"description": "ok"}}}},
            "/readyz": {"get": {"summary": "Readiness: assets loaded and a decode slot free", "responses": {"200": {"description": "ready"}, "503": {"$ref": "#/components/responses/Error"}}}},
            "/metrics": {"get": {"summary": "Prometheus metrics", "responses": {"200": {"description": "text exposition format"}}}},
            "/v1/openapi.json": {"get": {"summary": "This document", "responses": {"200": {"description": "OpenAPI 3.1"}}}},
            "/v1/assets": {"get": {"summary": "Catalog", "responses": {"200": {"description": "{\"assets\": [AssetSummary]}"}}}},
            "/v1/assets/{id}": {
                "parameters": [id],
                "get": {"summary": "Asset metadata", "responses": {"200": {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/AssetSummary"}}}, "description": "metadata"}, "404": {"$ref": "#/components/responses/Error"}}},
                "put": {"summary": "Upload an asset file (authorised before its body is read; validated, within the server's max_asset_pixels and max_decode_mib, before it is stored; atomic; concurrent writers of one id serialise)", "security": [{"bearer": []}],
                        "requestBody": {"content": {"application/octet-stream": {}}},
                        "responses": {"200": {"description": "replaced"}, "201": {"description": "created"}, "401": {"$ref": "#/components/responses/Error"}, "403": {"description": "the server takes no writes (started with no write token)", "$ref": "#/components/responses/Error"}, "413": {"$ref": "#/components/responses/Error"}, "422": {"$ref": "#/components/responses/Error"}, "503": {"description": "storage_unavailable: the asset store could not be written (nothing changed)", "$ref": "#/components/responses/Error"}}},
                "delete": {"summary": "Delete an asset", "security": [{"bearer": []}], "responses": {"204": {"description": "deleted"}, "401": {"$ref": "#/components/responses/Error"}, "403": {"description": "the server takes no writes (started with no write token)", "$ref": "#/components/responses/Error"}, "404": {"$ref": "#/components/responses/Error"}, "503": {"description": "storage_unavailable: the asset store could not be written (nothing changed)", "$ref": "#/components/responses/Error"}}}
            },
            "/v1/assets/{id}/file": {"get": {"summary": "The asset's file as stored (the bytes of its own format version), whole or one byte range (Range: bytes=FIRST-LAST; a suffix longer than the file is all of it), streamed; strong ETag per version, If-None-Match (304), If-Match (412), If-Range; HEAD reads nothing. What a client that decodes by itself reads, only the chunks it needs (the browser's WebAssembly reader); CORS exposes Content-Range, Content-Length and ETag", "parameters": [id, {"name": "Range", "in": "header", "required": false, "schema": {"type": "string"}, "description": "One byte range, bytes=FIRST-LAST, FIRST- or -SUFFIX"}, {"name": "If-None-Match", "in": "header", "required": false, "schema": {"type": "string"}}, {"name": "If-Match", "in": "header", "required": false, "schema": {"type": "string"}}, {"name": "If-Range", "in": "header", "required": false, "schema": {"type": "string"}}], "responses": {"200": {"description": "The whole file", "content": {"application/octet-stream": {}}}, "206": {"description": "The range asked, with Content-Range", "content": {"application/octet-stream": {}}}, "304": {"description": "Not modified (If-None-Match names its ETag)"}, "404": {"$ref": "#/components/responses/Error"}, "412": {"$ref": "#/components/responses/Error"}, "416": {"$ref": "#/components/responses/Error"}, "503": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/tilejson.json": {"get": {"summary": "TileJSON 3.0.0 for MapLibre (raster or raster-dem source)", "parameters": [id], "responses": {"200": {"description": "TileJSON"}, "404": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/tiles/{z}/{x}/{y}.{format}": {"get": {
                "summary": "A WebMercatorQuad tile (georeferenced assets) or a tile of the unit square (others), decoded by continuous extraction; filtered at zooms coarser than the source. 404 wholly outside the asset; a tile that overlaps it in any part is 200 (nodata where it is not).",
                "parameters": [id,
                    param("z", "path", json!({"type": "integer", "minimum": 0, "maximum": 24}), "Zoom"),
                    param("x", "path", json!({"type": "integer"}), "Column"),
                    param("y", "path", json!({"type": "integer"}), "Row (from the north)"),
                    param("format", "path", json!({"enum": ["png", "webp", "f32"]}), "png, webp (lossless: the same pixels; not with encoding=gray16), or f32 (little-endian float32 heights)"),
                    iterations.clone(),
                    tolerance.clone(),
                    backend.clone(),
                    param("tilesize", "query", json!({"enum": [256, 512]}), "Tile size"),
                    param("encoding", "query", json!({"enum": names::<HeightEncoding>()}), "Height packing of png and webp tiles (MapLibre's formulas); refused with .f32"),
                    param("rescale", "query", json!({"type": "string"}), "min,max for visual PNGs of heights"),
                    param("colormap", "query", json!({"enum": names::<Colormap>()}), "Colour ramp for visual PNGs of heights"),
                    param("hillshade", "query", json!({"type": "boolean"}), "Hillshade visual PNGs of heights (sun at 315 degrees, 45 degrees up)"),
                    param("precision", "query", json!({"enum": names::<Precision>(), "default": "bound"}), "terrainrgb and terrarium tiles: bound rounds heights to the largest power-of-two multiple of the encoding's unit (0.1 m, 1/256 m) that is at most half the tile's X-Error-Bound, which then includes the rounding (smaller PNGs; assets without a source-error map keep full precision); full keeps every unit")],
                "responses": ok_tile}},
            "/v1/assets/{id}/layer.json": {"get": {"summary": "Cesium terrain layer (quantized-mesh-1.0, geographic TMS scheme, EPSG:4326) of a georeferenced height field: tile URLs relative to this document, the levels and the tiles available at each", "parameters": [id], "responses": {"200": {"description": "layer.json"}, "400": {"$ref": "#/components/responses/Error"}, "404": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/terrain/{z}/{x}/{y}.terrain": {"get": {
                "summary": "A quantized-mesh-1.0 tile (Cesium terrain; TMS rows from the south, two root tiles): an adaptive mesh of a grid of decoded heights (65 x 65, or past the source's resolution as fine as its cells, each vertex the surface filtered over a cell unless iterations or tolerance asks for the continuation's detail) within the level's geometric error (Cesium's, 77,067 m at level 0, halved each level), measured on the globe; X-Convergence-Bound is the decode's bound plus that error, X-Error-Bound adds the source error. 404 wholly outside the asset.",
                "parameters": [id,
                    param("z", "path", json!({"type": "integer", "minimum": 0}), "Level"),
                    param("x", "path", json!({"type": "integer"}), "Column (from 180 degrees west)"),
                    param("y", "path", json!({"type": "integer"}), "Row (from the south)"),
                    iterations.clone(), tolerance.clone(), backend.clone()],
                "responses": {"200": {"description": "The tile", "headers": {"X-Error-Bound": {"schema": {"type": "number"}}, "X-Convergence-Bound": {"schema": {"type": "number"}}, "ETag": {"schema": {"type": "string"}}}, "content": {"application/vnd.quantized-mesh": {}}}, "304": {"description": "Not modified (If-None-Match)"}, "400": {"$ref": "#/components/responses/Error"}, "404": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/point": {"get": {"summary": "Value at a unit point (non-georeferenced assets); for volumes, the signed distance at world point x, y, z (DistanceResult)", "parameters": [id, param("x", "query", json!({"type": "number"}), "0..1 (volumes: world units)"), param("y", "query", json!({"type": "number"}), "0..1 (volumes: world units)"), param("z", "query", json!({"type": "number"}), "volumes only: world units"), iterations.clone(), tolerance.clone()],
                "responses": {"200": {"content": {"application/json": {"schema": {"oneOf": [{"$ref": "#/components/schemas/PointResult"}, {"$ref": "#/components/schemas/DistanceResult"}]}}}, "description": "value"}, "400": {"$ref": "#/components/responses/Error"}, "404": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/point/{coords}": {"get": {"summary": "Value at lon,lat", "parameters": [id, param("coords", "path", json!({"type": "string"}), "lon,lat"), iterations.clone(), tolerance.clone()],
                "responses": {"200": {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/PointResult"}}}, "description": "value"}, "400": {"$ref": "#/components/responses/Error"}, "404": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/points": {"post": {"summary": "Values at many points, in order (JSON or application/x-bincode)", "parameters": [id, backend.clone()],
                "requestBody": {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/PointsRequest"}}, "application/x-bincode": {}}},
                "responses": {"200": {"content": {"application/json": {"schema": {"type": "object", "properties": {"results": {"type": "array", "items": {"$ref": "#/components/schemas/PointResult"}}}}}, "application/x-bincode": {}}, "description": "values"}, "400": {"$ref": "#/components/responses/Error"}, "413": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/region": {"get": {"summary": "A window at any resolution", "parameters": [id,
                    param("bbox", "query", json!({"type": "string"}), "minx,miny,maxx,maxy (lon/lat, or unit coordinates)"),
                    param("width", "query", json!({"type": "integer"}), "pixels"), param("height", "query", json!({"type": "integer"}), "pixels"),
                    iterations.clone(), tolerance.clone(), backend.clone(), param("format", "query", json!({"enum": names::<RegionFormat>()}), "output (tif: float32 GeoTIFF of heights)")],
                "responses": {"200": {"description": "image or float32 samples (streamed)"}, "400": {"$ref": "#/components/responses/Error"}, "413": {"description": "too_expensive: the request needs more memory than the server's max_decode_mib", "$ref": "#/components/responses/Error"}, "503": {"description": "busy: large requests fill the server (refused within 1.5 s, with Retry-After); chunk_unavailable: a chunk could not be read (Retry-After)", "$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/mesh": {"get": {"summary": "Terrain mesh of a region (a regular grid, or with max_error an adaptive right-triangulated irregular network), or the surface of a volume in a box (marching over the continuous decode)", "parameters": [id,
                    param("bbox", "query", json!({"type": "string"}), "minx,miny,maxx,maxy (volumes: x0,y0,z0,x1,y1,z1 in the mesh's units; default: the whole asset)"),
                    param("resolution", "query", json!({"type": "integer", "minimum": 2, "maximum": 2048}), "vertices a side (volumes: samples along the box's longest side, at most 512, default the encoded grid)"),
                    param("max_error", "query", json!({"type": "number", "minimum": 0}), "height fields: an adaptive triangulation of the next 2^k + 1 grid whose surface stays within this many height units of every decoded height (added to X-Error-Bound)"),
                    iterations, tolerance, backend, param("format", "query", json!({"enum": names::<MeshFormat>()}), "file format")],
                "responses": {"200": {"description": "mesh file (streamed)"}, "400": {"$ref": "#/components/responses/Error"}, "413": {"description": "too_expensive: the request needs more memory than the server's max_decode_mib", "$ref": "#/components/responses/Error"}, "503": {"description": "busy: large requests fill the server (refused within 1.5 s, with Retry-After); chunk_unavailable: a chunk could not be read (Retry-After)", "$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/curve": {"get": {"summary": "A curve asset as GeoJSON at any level: one LineString Feature per input ring, in order; the foreign member `fractile` gives the level, the finest level and the Hausdorff error bound (in `units`)", "parameters": [id,
                    param("level", "query", json!({"type": "integer", "minimum": 0}), "0 is the coarsest; default the input's finest; deeper levels continue the details self-similarly"),
                    param("control", "query", json!({"type": "boolean"}), "answer each ring's base control points (what a `control` deformation moves)")],
                "responses": {"200": {"description": "GeoJSON FeatureCollection", "content": {"application/geo+json": {}}}, "400": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/curve/deform": {"post": {"summary": "Deforms a curve asset (stateless) and answers GeoJSON: move control points (details follow the rotation and scale), scale or rotate the details of the finer levels, or move one point of a level with its neighbours", "parameters": [id],
                "requestBody": {"required": true, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/DeformRequest"}}}},
                "responses": {"200": {"description": "GeoJSON FeatureCollection", "content": {"application/geo+json": {}}}, "400": {"$ref": "#/components/responses/Error"}}}}
        },
        "components": {
            "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"}},
            "responses": {"Error": {"description": "An error", "content": {"application/json": {"schema": {"type": "object", "required": ["detail", "code"], "properties": {"detail": {"type": "string"}, "code": {"type": "string", "enum": codes}}}}}}},
            "schemas": {
                "AssetSummary": {"type": "object", "properties": {"id": {"type": "string"}, "kind": {"enum": ["Image", "HeightField", "Volume", "Curve"]}, "width": {"type": "integer"}, "height": {"type": "integer"}, "bounds": {"type": ["array", "null"]}, "epsg": {"type": ["integer", "null"], "description": "EPSG code of the grid's CRS as its file names it, 4326 for geographic grids (requests take lon/lat whatever it is)"}, "value_range": {"type": "array"}, "units": {"type": ["string", "null"]}, "codec": {"type": "string"}, "bytes": {"type": "integer"}, "ratio": {"type": "number"}}},
                "PointsRequest": {"type": "object", "required": ["points"], "properties": {"points": {"type": "array", "items": {"type": "array", "minItems": 2, "maxItems": 2}}, "iterations": {"type": ["integer", "null"]}, "tolerance": {"type": ["number", "null"]}}},
                "DistanceResult": {"type": "object", "properties": {"coordinates": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}, "distance": {"type": ["number", "null"]}, "error_bound": {"type": ["number", "null"]}, "iterations": {"type": "integer"}, "outside": {"type": "boolean"}}},
                "DeformRequest": {"type": "object", "required": ["deformations"], "properties": {"level": {"type": ["integer", "null"]}, "deformations": {"type": "array", "items": {"oneOf": [
                    {"type": "object", "required": ["type", "ring", "points"], "properties": {"type": {"const": "control"}, "ring": {"type": "integer"}, "points": {"type": "array", "items": {"type": "array", "minItems": 2, "maxItems": 2}}}},
                    {"type": "object", "required": ["type", "from_level", "scale"], "properties": {"type": {"const": "details"}, "from_level": {"type": "integer"}, "scale": {"type": "number"}, "rotate_degrees": {"type": "number"}, "ring": {"type": ["integer", "null"]}}},
                    {"type": "object", "required": ["type", "ring", "level", "index", "to"], "properties": {"type": {"const": "local"}, "ring": {"type": "integer"}, "level": {"type": "integer"}, "index": {"type": "integer"}, "to": {"type": "array", "minItems": 2, "maxItems": 2}, "radius": {"type": "integer"}}}]}}}},
                "PointResult": {"type": "object", "properties": {"coordinates": {"type": "array"}, "values": {"type": ["array", "null"]}, "error_bound": {"type": ["number", "null"], "description": "Bound on |value - source|: the asset's measured source error where the point lies (between cells, against the source's bilinear interpolation; on a cell centre of an asset encoded with a largest error E, at most E) plus convergence_bound; null outside and for assets encoded before format version 5"}, "convergence_bound": {"type": ["number", "null"], "description": "Bound on the distance to the fractal's attractor: what progressive refinement stops on"}, "iterations": {"type": "integer"}, "outside": {"type": "boolean"}}}
            }
        }
    });
    add_volume_tiles(&mut doc, [id, iterations, tolerance, backend]);
    doc
}

/// The paths of a volume's 3D Tiles (tileset, content, subtrees) added to [`document`]'s.
fn add_volume_tiles(doc: &mut Value, [id, iterations, tolerance, backend]: [Value; 4]) {
    let volumes = json!({
    "/v1/assets/{id}/tileset.json": {"get": {"summary": "A volume as OGC 3D Tiles 1.1: implicit octree tiling (subtreeLevels 3), the root box the volume's grid cube, each level's geometricError half its parent's and at least its sampling's (sqrt(3) x the sample spacing) plus the decode's bound and the encode's largest field error, in mesh units; levels down to 4 times finer than the encoded grid (continuous decoding)", "parameters": [id,
                    param("lon", "query", json!({"type": "number"}), "longitude of the volume's origin on WGS84 (with lat): the root's transform is the east-north-up frame there"),
                    param("lat", "query", json!({"type": "number"}), "latitude of the volume's origin (with lon)"),
                    param("height", "query", json!({"type": "number"}), "metres above the ellipsoid (default 0)"),
                    param("scale", "query", json!({"type": "number", "exclusiveMinimum": 0}), "metres a mesh unit (default 1)"),
                    param("compression", "query", json!({"type": "string", "enum": ["meshopt", "plain"]}), "plain: the content template asks for plain tiles (for glTF readers without EXT_meshopt_compression)"),
                    iterations.clone(), tolerance.clone()],
                "responses": {"200": {"description": "tileset.json", "content": {"application/json": {}}}, "400": {"description": "not_volume: the asset is not a volume; bad_point: a placement out of range", "$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/3dtiles/{level}/{x}/{y}/{file}": {"get": {"summary": "A 3D tile's content: the surface inside the tile's box, 16 cells a side (glTF 2.0 binary: positions, normals, indices, quantized with KHR_mesh_quantization; y up as glTF has it); gzipped to clients that accept it (Vary: Accept-Encoding)", "parameters": [id,
                    param("level", "path", json!({"type": "integer"}), "octree level"),
                    param("x", "path", json!({"type": "integer"}), "index along x"), param("y", "path", json!({"type": "integer"}), "index along y"),
                    param("file", "path", json!({"type": "string"}), "{z}.glb, z the index along z"),
                    param("compression", "query", json!({"type": "string", "enum": ["meshopt", "plain"], "default": "meshopt"}), "meshopt: buffers through EXT_meshopt_compression where that makes the tile smaller; plain: KHR_mesh_quantization alone"),
                    iterations.clone(), tolerance.clone(), backend.clone()],
                "responses": {"200": {"description": "GLB", "headers": {"X-Error-Bound": {"schema": {"type": "number"}}, "ETag": {"schema": {"type": "string"}}}, "content": {"model/gltf-binary": {}}}, "304": {"description": "Not modified (If-None-Match)"}, "400": {"$ref": "#/components/responses/Error"}, "404": {"description": "no_tile: no such tile, or its box holds no surface (its subtree lists no content)", "$ref": "#/components/responses/Error"}, "503": {"$ref": "#/components/responses/Error"}}}},
            "/v1/assets/{id}/3dtiles/subtrees/{level}/{x}/{y}/{file}": {"get": {"summary": "A subtree of the implicit octree (3D Tiles 1.1 binary .subtree): which tiles exist, which hold a surface, which child subtrees exist", "parameters": [id,
                    param("level", "path", json!({"type": "integer"}), "a multiple of 3"),
                    param("x", "path", json!({"type": "integer"}), "index along x"), param("y", "path", json!({"type": "integer"}), "index along y"),
                    param("file", "path", json!({"type": "string"}), "{z}.subtree"),
                    iterations.clone(), tolerance.clone(), backend.clone()],
                "responses": {"200": {"description": "subtree", "content": {"application/octet-stream": {}}}, "304": {"description": "Not modified (If-None-Match)"}, "400": {"$ref": "#/components/responses/Error"}, "404": {"$ref": "#/components/responses/Error"}, "503": {"$ref": "#/components/responses/Error"}}}}
    });
    if let (Some(paths), Value::Object(volumes)) = (doc["paths"].as_object_mut(), volumes) {
        paths.extend(volumes);
    }
}
