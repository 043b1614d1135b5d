//! The thin client of a fractile server.
//!
//! It decodes no fractal: it asks the server for answers at a number of iterations and reads
//! back the a-priori error bound the server returns with each one. What it adds is the loop on
//! top of that ([`refine`]: more iterations until the answer stops changing, the bound is small
//! enough, or time runs out), the choice of tiles for a camera ([`view`]), and a load generator
//! ([`mod@bench`]). Every endpoint of the server is one typed method of [`Client`]; the wire types
//! come from `fractile-proto`, which the server writes with.

pub mod bench;
mod error;
pub mod refine;
mod request;
pub mod tile;
mod tileset;
pub mod view;

use std::time::{Duration, Instant};

pub use error::ClientError;
pub use fractile_proto::query::{Backend, Choice, MeshFormat, Precision, RegionFormat};
pub use fractile_proto::{
    AssetKind, AssetSummary, BINARY_MEDIA_TYPE, Catalog, DistanceResult, ErrorBody, LayerJson,
    PointResult, PointsRequest, PointsResponse, TileJson, TileRange,
};
pub use request::{
    MeshFile, MeshRequest, PointsEncoding, Region, RegionRequest, Uploaded, VolumeMeshRequest,
};
use reqwest::header;
pub use tile::{Tile, TileAddress, TileEncoding, TileRequest};
pub use tileset::Fetched;

/// A server's base URL plus the credentials writes need.
#[derive(Clone, Debug)]
pub struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
    backend: Option<Backend>,
}

/// Appends `?a=b&c=d` for the parameters that are set.
/// The parameters that are set, for reqwest's `.query()` (which percent-encodes them).
fn query(params: &[(&'static str, Option<String>)]) -> Vec<(&'static str, String)> {
    params
        .iter()
        .filter_map(|(k, v)| v.clone().map(|v| (*k, v)))
        .collect()
}

fn bbox(b: [f64; 4]) -> String {
    format!("{},{},{},{}", b[0], b[1], b[2], b[3])
}

/// The `X-Error-Bound` header of an answer.
/// `X-Convergence-Bound` (required) and `X-Error-Bound` (present for assets with a
/// source-error map).
fn bounds(r: &reqwest::Response) -> Result<(f32, Option<f32>), ClientError> {
    let number = |name: &str| {
        r.headers()
            .get(name)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse().ok())
    };
    let convergence = number("x-convergence-bound")
        .ok_or_else(|| ClientError::malformed("answer", "no X-Convergence-Bound header"))?;
    Ok((convergence, number("x-error-bound")))
}

impl Client {
    /// A client of the server at `base` (e.g. `http://127.0.0.1:8080`; without a scheme,
    /// `http://` is assumed).
    pub fn new(base: &str) -> Result<Client, ClientError> {
        // `127.0.0.1:8080` or `localhost:8080`, as the default is often written: plain HTTP,
        // as curl takes them (`localhost:8080` would otherwise parse as a URL of scheme
        // `localhost`).
        let owned;
        let base = if base.contains("://") {
            base
        } else {
            owned = format!("http://{base}");
            &owned
        };
        let url = reqwest::Url::parse(base)
            .map_err(|e| ClientError::malformed("server URL", format!("{base:?}: {e}")))?;
        if !matches!(url.scheme(), "http" | "https") {
            return Err(ClientError::malformed(
                "server URL",
                format!("{base:?}: the scheme must be http or https"),
            ));
        }
        let http = reqwest::Client::builder()
            .user_agent(concat!("fractile-client/", env!("CARGO_PKG_VERSION")))
            .connect_timeout(Duration::from_secs(10))
            .timeout(Duration::from_secs(120))
            .build()
            .map_err(ClientError::Transport)?;
        Ok(Client {
            http,
            base: base.trim_end_matches('/').to_string(),
            token: None,
            backend: None,
        })
    }

    /// Sends `Authorization: Bearer <token>` with uploads and deletes.
    pub fn with_token(mut self, token: Option<String>) -> Client {
        self.token = token;
        self
    }

    /// The same client asking the server to decode on `backend` (`None`: the server's setting)
    /// for every tile, region, mesh and points batch. A clone is cheap, so one request can use
    /// its own.
    pub fn with_backend(mut self, backend: Option<Backend>) -> Client {
        self.backend = backend;
        self
    }

    /// The base URL.
    pub fn base(&self) -> &str {
        &self.base
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// `/v1/assets/{id}{rest}`, refusing ids the server would refuse: an id is a URL path
    /// segment, and `..` in one would be normalised away before it left this machine.
    fn asset_path(&self, id: &str, rest: &str) -> Result<String, ClientError> {
        if !fractile_proto::valid_asset_id(id) {
            return Err(ClientError::malformed(
                "asset id",
                format!("{id:?} must be 1-64 letters, digits, '-' or '_'"),
            ));
        }
        Ok(format!("/v1/assets/{id}{rest}"))
    }

    /// Sends a request and turns error statuses into [`ClientError`] with the server's detail.
    async fn send(&self, req: reqwest::RequestBuilder) -> Result<reqwest::Response, ClientError> {
        let r = req.send().await.map_err(ClientError::Transport)?;
        if r.status().is_success() {
            return Ok(r);
        }
        let status = r.status().as_u16();
        let text = r.text().await.unwrap_or_default();
        Err(ClientError::from_answer(status, &text))
    }

    /// The body of a `GET` of `path`.
    async fn get_bytes(&self, path: &str) -> Result<Vec<u8>, ClientError> {
        let r = self.send(self.http.get(self.url(path))).await?;
        Ok(r.bytes().await.map_err(ClientError::Transport)?.to_vec())
    }

    async fn get_json<T: serde::de::DeserializeOwned>(&self, path: &str) -> Result<T, ClientError> {
        self.get_json_query(path, &[]).await
    }

    async fn get_json_query<T: serde::de::DeserializeOwned>(
        &self,
        path: &str,
        q: &[(&'static str, String)],
    ) -> Result<T, ClientError> {
        let r = self.send(self.http.get(self.url(path)).query(q)).await?;
        let bytes = r.bytes().await.map_err(ClientError::Transport)?;
        serde_json::from_slice(&bytes).map_err(|e| ClientError::malformed(path, e.to_string()))
    }

    /// `GET /readyz`: whether the server answers.
    pub async fn ready(&self) -> Result<(), ClientError> {
        self.send(self.http.get(self.url("/readyz"))).await?;
        Ok(())
    }

    /// `GET /v1/assets`: every asset.
    pub async fn assets(&self) -> Result<Vec<AssetSummary>, ClientError> {
        Ok(self.get_json::<Catalog>("/v1/assets").await?.assets)
    }

    /// `GET /v1/assets/{id}`: one asset's metadata.
    pub async fn asset(&self, id: &str) -> Result<AssetSummary, ClientError> {
        self.get_json(&self.asset_path(id, "")?).await
    }

    /// `GET /v1/assets/{id}/tilejson.json`.
    pub async fn tilejson(&self, id: &str) -> Result<TileJson, ClientError> {
        self.get_json(&self.asset_path(id, "/tilejson.json")?).await
    }

    /// `GET /v1/assets/{id}/file`: the asset's file as stored, whole, or `first..=last` of its
    /// bytes (a `Range` request; the server answers one range, and whole files up to 64 MiB).
    pub async fn file_bytes(
        &self,
        id: &str,
        range: Option<(u64, u64)>,
    ) -> Result<Vec<u8>, ClientError> {
        let mut req = self.http.get(self.url(&self.asset_path(id, "/file")?));
        if let Some((first, last)) = range {
            req = req.header(reqwest::header::RANGE, format!("bytes={first}-{last}"));
        }
        let r = self.send(req).await?;
        Ok(r.bytes().await.map_err(ClientError::Transport)?.to_vec())
    }

    /// `GET /v1/assets/{id}/layer.json`: the Cesium terrain layer of a georeferenced DEM.
    pub async fn layer_json(&self, id: &str) -> Result<LayerJson, ClientError> {
        self.get_json(&self.asset_path(id, "/layer.json")?).await
    }

    /// `GET /v1/assets/{id}/terrain/{z}/{x}/{y}.terrain` asked for as CesiumJS asks (vertex
    /// normals, gzip), its body left as sent: what the load generator times.
    pub(crate) async fn terrain_tile_body(
        &self,
        id: &str,
        (z, x, y): (u8, u32, u32),
    ) -> Result<TileBody, ClientError> {
        let path = self.asset_path(id, &format!("/terrain/{z}/{x}/{y}.terrain"))?;
        let q = query(&[("backend", self.backend.map(|b| b.name().to_string()))]);
        let start = Instant::now();
        let req = self
            .http
            .get(self.url(&path))
            .query(&q)
            .header(
                header::ACCEPT,
                "application/vnd.quantized-mesh;extensions=octvertexnormals,application/octet-stream;q=0.9",
            )
            .header(header::ACCEPT_ENCODING, "gzip");
        let r = self.send(req).await?;
        TileBody::read(r, start).await
    }

    /// `PUT /v1/assets/{id}`: stores an asset file (made by `fractile encode`).
    pub async fn upload(&self, id: &str, file: Vec<u8>) -> Result<Uploaded, ClientError> {
        let mut req = self
            .http
            .put(self.url(&self.asset_path(id, "")?))
            .header(header::CONTENT_TYPE, "application/octet-stream")
            .body(file);
        if let Some(t) = &self.token {
            req = req.bearer_auth(t);
        }
        let r = self.send(req).await?;
        let created = r.status() == reqwest::StatusCode::CREATED;
        let bytes = r.bytes().await.map_err(ClientError::Transport)?;
        let summary = serde_json::from_slice(&bytes)
            .map_err(|e| ClientError::malformed("upload answer", e.to_string()))?;
        Ok(Uploaded { summary, created })
    }

    /// `DELETE /v1/assets/{id}`.
    pub async fn delete(&self, id: &str) -> Result<(), ClientError> {
        let mut req = self.http.delete(self.url(&self.asset_path(id, "")?));
        if let Some(t) = &self.token {
            req = req.bearer_auth(t);
        }
        self.send(req).await?;
        Ok(())
    }

    /// `GET /v1/assets/{id}/tiles/{z}/{x}/{y}.{png|f32}`: one tile, its heights decoded back to
    /// floats for the height encodings. A [`TileEncoding::Gray16`] tile needs the asset's value
    /// range, fetched with one more request.
    pub async fn tile(&self, id: &str, req: &TileRequest) -> Result<Tile, ClientError> {
        let raw = self.tile_body(id, req).await?;
        let range = match req.encoding {
            TileEncoding::Gray16 => {
                let a = self.asset(id).await?;
                Some(a.value_range)
            }
            _ => None,
        };
        Tile::decode(req, raw.body, raw.bounds, raw.etag, raw.elapsed, range)
    }

    /// A tile's body as sent, undecoded: what the load generator times, so that the client's
    /// PNG decoding does not take the cores the server is measured on.
    pub(crate) async fn tile_body(
        &self,
        id: &str,
        req: &TileRequest,
    ) -> Result<TileBody, ClientError> {
        let TileAddress { z, x, y } = req.address;
        let ext = if req.encoding == TileEncoding::F32 {
            "f32"
        } else {
            "png"
        };
        let q = query(&[
            (
                "encoding",
                req.encoding.query_name().map(|e| e.name().to_string()),
            ),
            ("iterations", req.iterations.map(|n| n.to_string())),
            ("tolerance", req.tolerance.map(|t| t.to_string())),
            (
                "tilesize",
                (req.tile_size != 256).then(|| req.tile_size.to_string()),
            ),
            ("backend", self.backend.map(|b| b.name().to_string())),
            ("precision", req.precision.map(|p| p.name().to_string())),
        ]);
        let path = self.asset_path(id, &format!("/tiles/{z}/{x}/{y}.{ext}"))?;
        let start = Instant::now();
        let r = self.send(self.http.get(self.url(&path)).query(&q)).await?;
        TileBody::read(r, start).await
    }

    /// `GET /v1/assets/{id}/point/{lon},{lat}` (georeferenced assets).
    pub async fn point_lonlat(
        &self,
        id: &str,
        lon: f64,
        lat: f64,
        iterations: Option<u32>,
    ) -> Result<PointResult, ClientError> {
        let q = query(&[("iterations", iterations.map(|n| n.to_string()))]);
        self.get_json_query(&self.asset_path(id, &format!("/point/{lon},{lat}"))?, &q)
            .await
    }

    /// `GET /v1/assets/{id}/point?x=&y=` (unit coordinates, any asset).
    pub async fn point_unit(
        &self,
        id: &str,
        x: f64,
        y: f64,
        iterations: Option<u32>,
    ) -> Result<PointResult, ClientError> {
        let q = query(&[
            ("x", Some(x.to_string())),
            ("y", Some(y.to_string())),
            ("iterations", iterations.map(|n| n.to_string())),
        ]);
        self.get_json_query(&self.asset_path(id, "/point")?, &q)
            .await
    }

    /// `GET /v1/assets/{id}/point?x=&y=&z=`: the signed distance of a volume asset at a world
    /// point, with its bound.
    pub async fn distance(
        &self,
        id: &str,
        p: [f64; 3],
        iterations: Option<u32>,
    ) -> Result<DistanceResult, ClientError> {
        let q = query(&[
            ("x", Some(p[0].to_string())),
            ("y", Some(p[1].to_string())),
            ("z", Some(p[2].to_string())),
            ("iterations", iterations.map(|n| n.to_string())),
        ]);
        self.get_json_query(&self.asset_path(id, "/point")?, &q)
            .await
    }

    /// `GET /v1/assets/{id}/curve?level=N`: a curve asset as a GeoJSON FeatureCollection (one
    /// Feature per input ring; `fractile.error_bound` is the level's Hausdorff bound). `None`:
    /// the input's finest level.
    pub async fn curve(
        &self,
        id: &str,
        level: Option<usize>,
    ) -> Result<serde_json::Value, ClientError> {
        let q = query(&[("level", level.map(|n| n.to_string()))]);
        self.get_json_query(&self.asset_path(id, "/curve")?, &q)
            .await
    }

    /// `POST /v1/assets/{id}/curve/deform`: the deformed curve as GeoJSON (the stored asset is
    /// unchanged).
    pub async fn deform_curve(
        &self,
        id: &str,
        req: &fractile_proto::DeformRequest,
    ) -> Result<serde_json::Value, ClientError> {
        let url = self.url(&self.asset_path(id, "/curve/deform")?);
        let r = self.send(self.http.post(url).json(req)).await?;
        let bytes = r.bytes().await.map_err(ClientError::Transport)?;
        serde_json::from_slice(&bytes)
            .map_err(|e| ClientError::malformed("curve answer", e.to_string()))
    }

    /// `POST /v1/assets/{id}/points`: a batch, in JSON or binary.
    pub async fn points(
        &self,
        id: &str,
        req: &PointsRequest,
        encoding: PointsEncoding,
    ) -> Result<PointsResponse, ClientError> {
        let q = query(&[("backend", self.backend.map(|b| b.name().to_string()))]);
        let url = self.url(&self.asset_path(id, "/points")?);
        match encoding {
            PointsEncoding::Json => {
                let r = self.send(self.http.post(url).query(&q).json(req)).await?;
                let bytes = r.bytes().await.map_err(ClientError::Transport)?;
                serde_json::from_slice(&bytes)
                    .map_err(|e| ClientError::malformed("points answer", e.to_string()))
            }
            PointsEncoding::Binary => {
                let r = self
                    .send(
                        self.http
                            .post(url)
                            .query(&q)
                            .header(header::CONTENT_TYPE, BINARY_MEDIA_TYPE)
                            .header(header::ACCEPT, BINARY_MEDIA_TYPE)
                            .body(fractile_proto::encode(req)),
                    )
                    .await?;
                let bytes = r.bytes().await.map_err(ClientError::Transport)?;
                fractile_proto::decode(&bytes)
                    .map_err(|e| ClientError::malformed("points answer", e.to_string()))
            }
        }
    }

    /// `GET /v1/assets/{id}/region`.
    pub async fn region(&self, id: &str, req: &RegionRequest) -> Result<Region, ClientError> {
        let q = query(&[
            ("bbox", Some(bbox(req.bbox))),
            ("width", Some(req.width.to_string())),
            ("height", Some(req.height.to_string())),
            ("iterations", req.iterations.map(|n| n.to_string())),
            ("tolerance", req.tolerance.map(|t| t.to_string())),
            ("format", Some(req.format.name().to_string())),
            ("backend", self.backend.map(|b| b.name().to_string())),
        ]);
        let r = self
            .send(
                self.http
                    .get(self.url(&self.asset_path(id, "/region")?))
                    .query(&q),
            )
            .await?;
        let (convergence_bound, error_bound) = bounds(&r)?;
        let body = r.bytes().await.map_err(ClientError::Transport)?.to_vec();
        let values = if req.format == RegionFormat::F32 {
            let n = req.width as usize * req.height as usize;
            if n == 0 || body.len() % (4 * n) != 0 {
                return Err(ClientError::malformed(
                    "region",
                    format!("{} bytes for {n} float32 pixels", body.len()),
                ));
            }
            let floats: Vec<f32> = body
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            Some(floats.chunks(n).map(<[f32]>::to_vec).collect())
        } else {
            None
        };
        Ok(Region {
            width: req.width,
            height: req.height,
            body,
            values,
            convergence_bound,
            error_bound,
        })
    }

    /// `GET /v1/assets/{id}/mesh`: a terrain mesh.
    pub async fn mesh(&self, id: &str, req: &MeshRequest) -> Result<MeshFile, ClientError> {
        let q = query(&[
            ("bbox", req.bbox.map(bbox)),
            ("resolution", req.resolution.map(|n| n.to_string())),
            ("iterations", req.iterations.map(|n| n.to_string())),
            ("tolerance", req.tolerance.map(|t| t.to_string())),
            ("max_error", req.max_error.map(|e| e.to_string())),
            ("format", Some(req.format.name().to_string())),
            ("backend", self.backend.map(|b| b.name().to_string())),
        ]);
        self.get_mesh(id, &q).await
    }

    /// `GET /v1/assets/{id}/mesh` of a volume asset: its surface in a 3D box.
    pub async fn volume_mesh(
        &self,
        id: &str,
        req: &VolumeMeshRequest,
    ) -> Result<MeshFile, ClientError> {
        let q = query(&[
            (
                "bbox",
                req.bbox.map(|b| {
                    b.iter()
                        .map(|v| v.to_string())
                        .collect::<Vec<_>>()
                        .join(",")
                }),
            ),
            ("resolution", req.resolution.map(|n| n.to_string())),
            ("iterations", req.iterations.map(|n| n.to_string())),
            ("tolerance", req.tolerance.map(|t| t.to_string())),
            ("format", Some(req.format.name().to_string())),
            ("backend", self.backend.map(|b| b.name().to_string())),
        ]);
        self.get_mesh(id, &q).await
    }

    async fn get_mesh(
        &self,
        id: &str,
        q: &[(&'static str, String)],
    ) -> Result<MeshFile, ClientError> {
        let r = self
            .send(
                self.http
                    .get(self.url(&self.asset_path(id, "/mesh")?))
                    .query(q),
            )
            .await?;
        let (convergence_bound, error_bound) = bounds(&r)?;
        let content_type = r
            .headers()
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("application/octet-stream")
            .to_string();
        let body = r.bytes().await.map_err(ClientError::Transport)?.to_vec();
        Ok(MeshFile {
            body,
            content_type,
            convergence_bound,
            error_bound,
        })
    }
}

/// A tile as it came off the wire.
pub(crate) struct TileBody {
    pub(crate) body: Vec<u8>,
    /// `X-Convergence-Bound` and `X-Error-Bound`.
    pub(crate) bounds: (f32, Option<f32>),
    pub(crate) etag: Option<String>,
    pub(crate) elapsed: Duration,
}

impl TileBody {
    /// A tile answer's body, bounds and ETag, its time counted from `start`.
    async fn read(r: reqwest::Response, start: Instant) -> Result<TileBody, ClientError> {
        let bounds = bounds(&r)?;
        let etag = r
            .headers()
            .get(header::ETAG)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string);
        let body = r.bytes().await.map_err(ClientError::Transport)?.to_vec();
        Ok(TileBody {
            body,
            bounds,
            etag,
            elapsed: start.elapsed(),
        })
    }
}
