//! The inputs of an encode where they live (issue 78): GeoTIFFs (cloud-optimized ones read by
//! range) in a bucket (`s3://bucket/key.tif`, or every `.tif` under `s3://bucket/prefix/`), on
//! a web server (`https://.../x.tif`), or named by a list: a text file of locations (one a
//! line, `#` comments) or a STAC ItemCollection (the GeoJSON FeatureCollection of items that
//! public DEM catalogs publish; each item's data asset). Lists may themselves be local files,
//! objects or URLs. One [`Opener`] opens them all on one runtime and one HTTP client, with one
//! object store a bucket, so that thousands of inputs hold no thread or connection pool each.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use fractile_codec::chunked::ChunkSource;
use futures_util::TryStreamExt;
use object_store::ObjectStore;
use object_store::path::Path;

use crate::{READ_TIMEOUT, Runtime, http_client, is_remote, open_on, s3_store};

/// Largest list file read (a text list or a STAC ItemCollection): 64 MiB, some hundred
/// thousand items.
const MOST_LIST: u64 = 64 << 20;

/// Opens the inputs of one encode: lists them ([`Opener::list`]) and opens each by range
/// ([`Opener::open`]).
pub struct Opener {
    runtime: Arc<Runtime>,
    http: reqwest::Client,
    /// One object store a bucket (its connection pool shared by every object in it).
    stores: Mutex<HashMap<String, Arc<dyn ObjectStore>>>,
    /// The lengths of the objects a listing named (no request to ask them again).
    sizes: Mutex<HashMap<String, u64>>,
    /// What a STAC item says of its GeoTIFF's grid, by location: placed without reading its
    /// header ([`Opener::declared`]).
    declared: Mutex<HashMap<String, Declared>>,
}

/// What a STAC item says of its GeoTIFF (the projection and raster extensions): enough to
/// place it on a mosaic without reading its header, so that a part of a split encode opens
/// only the inputs its band of rows crosses. The reader checks it against the file's header
/// when it first reads cells.
#[derive(Clone, Debug, PartialEq)]
pub struct Declared {
    /// `proj:shape`: rows, then columns.
    pub shape: [usize; 2],
    /// `proj:transform`: the affine `[a, b, c, d, e, f]` (x = a col + b row + c, y = d col +
    /// e row + f), north up (b = d = 0).
    pub transform: [f64; 6],
    /// `proj:epsg` (or `proj:code` `EPSG:n`).
    pub epsg: Option<u32>,
    /// `raster:bands[0].data_type` (`int16`, `uint16`, `float32`, ...).
    pub data_type: String,
    /// `raster:bands[0].nodata`.
    pub nodata: Option<f64>,
}

impl Opener {
    /// An opener with its runtime and client (no request yet).
    pub fn new() -> std::io::Result<Opener> {
        Ok(Opener {
            runtime: Runtime::new()?,
            http: http_client(READ_TIMEOUT)?,
            stores: Mutex::new(HashMap::new()),
            sizes: Mutex::new(HashMap::new()),
            declared: Mutex::new(HashMap::new()),
        })
    }

    /// What the STAC item that listed `location` says of its grid, if it says all of it.
    pub fn declared(&self, location: &str) -> Option<Declared> {
        let declared = self.declared.lock().unwrap_or_else(|e| e.into_inner());
        declared.get(location).cloned()
    }

    /// The object store of `url`'s bucket (made on first use: building one costs about as
    /// much as a request) and `url`'s key.
    fn store(&self, url: &str) -> std::io::Result<(Arc<dyn ObjectStore>, Path)> {
        let (bucket, key) = url
            .trim_start_matches("s3://")
            .split_once('/')
            .unwrap_or((url, ""));
        let key = Path::from(key.trim_matches('/'));
        let mut stores = self.stores.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(store) = stores.get(bucket) {
            return Ok((store.clone(), key));
        }
        let (made, _) = s3_store(url)?;
        stores.insert(bucket.to_string(), made.clone());
        Ok((made, key))
    }

    /// `location` (a path, an `s3://` object or an `http(s)://` file) opened by range.
    pub fn open(&self, location: &str) -> std::io::Result<Box<dyn ChunkSource>> {
        if !is_remote(location) {
            return Ok(Box::new(fractile_codec::chunked::FileSource::open(
                std::path::Path::new(location),
            )?));
        }
        let store = match location.starts_with("s3://") {
            true => Some(self.store(location)?),
            false => None,
        };
        let known = self
            .sizes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(location)
            .copied();
        open_on(&self.runtime, &self.http, store, location, known)
    }

    /// The inputs `location` names, in order: every `.tif` / `.tiff` object under an `s3://`
    /// prefix that ends in `/` or names no TIFF (in key order); the locations a `.txt` list
    /// or a STAC ItemCollection (`.json`, `.geojson`) holds; `location` itself otherwise. A
    /// local folder stays a folder (the codec lists it).
    pub fn list(&self, location: &str) -> std::io::Result<Vec<String>> {
        let lower = location.to_ascii_lowercase();
        let tiff = lower.ends_with(".tif") || lower.ends_with(".tiff");
        if lower.ends_with(".txt") {
            let text = self.read_list(location)?;
            return Ok(text_list(&text, location));
        }
        if lower.ends_with(".json") || lower.ends_with(".geojson") {
            let text = self.read_list(location)?;
            let items = stac_items(&text, location)?;
            let mut sizes = self.sizes.lock().unwrap_or_else(|e| e.into_inner());
            let mut declared = self.declared.lock().unwrap_or_else(|e| e.into_inner());
            let mut out = Vec::with_capacity(items.len());
            for item in items {
                if let Some(size) = item.size {
                    sizes.insert(item.location.clone(), size);
                }
                if let Some(d) = item.declared {
                    declared.insert(item.location.clone(), d);
                }
                out.push(item.location);
            }
            return Ok(out);
        }
        if location.starts_with("s3://") && !tiff {
            return self.list_prefix(location);
        }
        Ok(vec![location.to_string()])
    }

    /// Every TIFF object under the prefix `url`, in key order.
    fn list_prefix(&self, url: &str) -> std::io::Result<Vec<String>> {
        let (store, key) = self.store(url)?;
        let bucket = url
            .trim_start_matches("s3://")
            .split('/')
            .next()
            .unwrap_or_default();
        let prefix = (!key.as_ref().is_empty()).then_some(&key);
        let objects: Vec<object_store::ObjectMeta> = self
            .runtime
            .block_on(store.list(prefix).try_collect::<Vec<_>>())?
            .map_err(std::io::Error::from)?;
        let mut keys: Vec<String> = Vec::with_capacity(objects.len());
        let mut sizes = self.sizes.lock().unwrap_or_else(|e| e.into_inner());
        for o in objects {
            let k = o.location.to_string();
            let lower = k.to_ascii_lowercase();
            if lower.ends_with(".tif") || lower.ends_with(".tiff") {
                sizes.insert(format!("s3://{bucket}/{k}"), o.size);
                keys.push(k);
            }
        }
        if keys.is_empty() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!("{url}: no GeoTIFF (.tif, .tiff) under this prefix"),
            ));
        }
        keys.sort();
        Ok(keys
            .into_iter()
            .map(|k| format!("s3://{bucket}/{k}"))
            .collect())
    }

    /// A list file's text (at most [`MOST_LIST`] bytes).
    fn read_list(&self, location: &str) -> std::io::Result<String> {
        let source = self.open(location)?;
        if source.len() > MOST_LIST {
            return Err(std::io::Error::other(format!(
                "{location}: a list of {} bytes (at most {MOST_LIST} are read)",
                source.len()
            )));
        }
        let bytes = source.read(0, source.len() as usize)?;
        String::from_utf8(bytes)
            .map_err(|_| std::io::Error::other(format!("{location}: a list that is not UTF-8")))
    }
}

/// `href` as a location: as it is when absolute (a scheme, or a root path), else relative to
/// the folder of `base` (the list that names it), as STAC and URL lists mean it.
fn resolve(href: &str, base: &str) -> String {
    if href.contains("://") || href.starts_with('/') {
        return href.to_string();
    }
    match base.rfind('/') {
        Some(i) => format!("{}/{}", &base[..i], href.trim_start_matches("./")),
        None => href.to_string(),
    }
}

/// The locations of a text list: one a line, blank lines and `#` comments skipped.
fn text_list(text: &str, base: &str) -> Vec<String> {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| resolve(l, base))
        .collect()
}

/// A STAC item's data asset: its location, and what the item says of it.
#[derive(Debug)]
struct Item {
    location: String,
    /// `file:size`.
    size: Option<u64>,
    declared: Option<Declared>,
}

/// What `item` (or its `asset`, which overrides it) says of the asset's grid, where it says
/// all of it (shape, a north-up transform, a data type).
fn declared_of(item: &serde_json::Value, asset: &serde_json::Value) -> Option<Declared> {
    let field = |name: &str| {
        let a = &asset[name];
        if a.is_null() {
            &item["properties"][name]
        } else {
            a
        }
    };
    let shape = field("proj:shape").as_array()?;
    let shape: Vec<usize> = shape
        .iter()
        .map(|v| v.as_u64().map(|v| v as usize))
        .collect::<Option<_>>()?;
    let transform = field("proj:transform").as_array()?;
    let transform: Vec<f64> = transform
        .iter()
        .map(serde_json::Value::as_f64)
        .collect::<Option<_>>()?;
    if shape.len() != 2 || transform.len() < 6 || transform[1] != 0.0 || transform[3] != 0.0 {
        return None;
    }
    let epsg = field("proj:epsg").as_u64().map(|e| e as u32).or_else(|| {
        field("proj:code")
            .as_str()
            .and_then(|c| c.strip_prefix("EPSG:"))
            .and_then(|c| c.parse().ok())
    });
    let band = &field("raster:bands")[0];
    Some(Declared {
        shape: [shape[0], shape[1]],
        transform: transform[..6].try_into().ok()?,
        epsg,
        data_type: band["data_type"].as_str()?.to_string(),
        nodata: band["nodata"].as_f64(),
    })
}

/// The data assets of a STAC ItemCollection, one an item, in the items' order: the asset
/// whose roles include `data` and whose type or href says GeoTIFF, else the assets named
/// `data`, `elevation` or `dem`, else the first whose href ends in `.tif` / `.tiff`. An item
/// with none is an error that names it (a catalog of other products, not a silent skip).
/// Paging (`links` with `rel: next`) is not followed: a search's pages are fetched first.
fn stac_items(text: &str, base: &str) -> std::io::Result<Vec<Item>> {
    let bad = |why: String| {
        std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{base}: {why}"))
    };
    let json: serde_json::Value =
        serde_json::from_str(text).map_err(|e| bad(format!("not JSON ({e})")))?;
    let Some(items) = json["features"].as_array() else {
        return Err(bad(
            "not a STAC ItemCollection (a FeatureCollection with features)".into(),
        ));
    };
    let tiff = |a: &serde_json::Value| {
        let href = a["href"].as_str().unwrap_or_default().to_ascii_lowercase();
        let kind = a["type"].as_str().unwrap_or_default();
        kind.contains("geotiff")
            || kind.contains("image/tiff")
            || href.ends_with(".tif")
            || href.ends_with(".tiff")
    };
    let mut out = Vec::with_capacity(items.len());
    for (i, item) in items.iter().enumerate() {
        let assets = item["assets"].as_object();
        let assets: Vec<(&String, &serde_json::Value)> = assets.into_iter().flatten().collect();
        let data = assets
            .iter()
            .find(|(_, a)| {
                a["roles"]
                    .as_array()
                    .is_some_and(|r| r.iter().any(|r| r == "data"))
                    && tiff(a)
            })
            .or_else(|| {
                assets
                    .iter()
                    .find(|(k, a)| ["data", "elevation", "dem"].contains(&k.as_str()) && tiff(a))
            })
            .or_else(|| assets.iter().find(|(_, a)| tiff(a)));
        let Some((_, asset)) = data else {
            let id = item["id"]
                .as_str()
                .map_or(format!("item {i}"), str::to_string);
            return Err(bad(format!("{id} has no GeoTIFF asset")));
        };
        let href = asset["href"].as_str().unwrap_or_default();
        out.push(Item {
            location: resolve(href, base),
            size: asset["file:size"].as_u64(),
            declared: declared_of(item, asset),
        });
    }
    if out.is_empty() {
        return Err(bad("an ItemCollection with no items".into()));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A STAC ItemCollection as Earth Search and Planetary Computer publish them (a data
    /// asset among thumbnails and metadata), relative hrefs resolved against the list.
    #[test]
    fn stac_items_name_their_data_assets() {
        let text = r#"{"type": "FeatureCollection", "features": [
          {"id": "a", "properties": {"proj:epsg": 4326, "proj:shape": [3600, 1800],
                                     "proj:transform": [0.001, 0, 6.0, 0, -0.001, 46.0, 0, 0, 1]},
           "assets": {
            "thumbnail": {"href": "a.png", "type": "image/png", "roles": ["thumbnail"]},
            "data": {"href": "s3://dem/a.tif", "type": "image/tiff; application=geotiff; profile=cloud-optimized", "roles": ["data"],
                     "file:size": 1234, "raster:bands": [{"data_type": "int16", "nodata": -32768}]}}},
          {"id": "b", "properties": {"proj:code": "EPSG:32616", "proj:shape": [10, 10],
                                     "proj:transform": [90, 5, 0, 0, -90, 0]},
           "assets": {"elevation": {"href": "./tiles/b.tif", "raster:bands": [{"data_type": "float32"}]}}},
          {"id": "c", "assets": {"metadata": {"href": "c.xml", "roles": ["metadata"]},
                                 "x": {"href": "https://h/c.TIFF"}}}]}"#;
        let items = stac_items(text, "https://catalog.example/dem/items.json").unwrap();
        let got: Vec<&str> = items.iter().map(|i| i.location.as_str()).collect();
        // a says its whole grid (the item's projection, its asset's band and size); b's grid
        // is rotated (placed from its header), c says nothing.
        assert_eq!(
            items[0].declared,
            Some(Declared {
                shape: [3600, 1800],
                transform: [0.001, 0.0, 6.0, 0.0, -0.001, 46.0],
                epsg: Some(4326),
                data_type: "int16".into(),
                nodata: Some(-32768.0),
            })
        );
        assert_eq!(items[0].size, Some(1234));
        assert!(items[1].declared.is_none() && items[2].declared.is_none());
        assert_eq!(
            got,
            [
                "s3://dem/a.tif",
                "https://catalog.example/dem/tiles/b.tif",
                "https://h/c.TIFF"
            ]
        );
        let none = r#"{"features": [{"id": "q", "assets": {"meta": {"href": "q.xml"}}}]}"#;
        let e = stac_items(none, "l.json").unwrap_err().to_string();
        assert!(e.contains("q has no GeoTIFF asset"), "{e}");
        assert!(stac_items("{}", "l.json").is_err());
    }

    #[test]
    fn text_lists_skip_comments_and_resolve_relative_lines() {
        let got = text_list(
            "# DEM tiles\n\ns3://b/x.tif\n  y.tif \n/abs/z.tif\n",
            "s3://b/lists/l.txt",
        );
        assert_eq!(got, ["s3://b/x.tif", "s3://b/lists/y.tif", "/abs/z.tif"]);
    }
}
