//! The rasters an encode reads, where they lie (issue 78): local files and folders (the
//! codec's `mosaic::open_rows`), and GeoTIFFs by URL (`s3://bucket/key.tif`, every TIFF under
//! `s3://bucket/prefix/`, `https://...tif`) or named by a list (a `.txt` of locations, a STAC
//! ItemCollection), read by range: a cloud-optimized GeoTIFF's header, then the tiles each
//! band of rows crosses (`fractile_codec::rows::RangedFile`). Listing and opening are
//! `fractile_remote::inputs`; the mosaic of them is the codec's.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use fractile_codec::mosaic::Mosaic;
use fractile_codec::rows::{GeoTiff, Header, KeptBudget, RangedFile, Rows, TiffSource};
use fractile_remote::inputs::{Declared, Opener};

/// An encode's inputs: their names (for the report) and their rows.
pub(super) struct Inputs {
    /// Each input file or object, in the mosaic's order.
    pub(super) names: Vec<String>,
    pub(super) rows: Box<dyn Rows>,
    /// The inputs read by range, for what they fetched.
    ranged: Vec<Arc<RangedFile>>,
    /// How many inputs were resampled onto the mosaic's grid.
    pub(super) resampled: usize,
}

impl Inputs {
    /// Bytes fetched by range so far, and in how many requests.
    pub(super) fn fetched(&self) -> (u64, u64) {
        self.ranged
            .iter()
            .map(|r| r.fetched())
            .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }

    /// A handle on what the inputs fetch, which outlives a borrow of their rows.
    pub(super) fn meter(&self) -> Meter {
        Meter(self.ranged.clone())
    }

    /// Whether any input is read by range.
    pub(super) fn remote(&self) -> bool {
        !self.ranged.is_empty()
    }
}

/// What an encode's inputs read by range have fetched.
pub(super) struct Meter(Vec<Arc<RangedFile>>);

impl Meter {
    /// Bytes and requests so far; `None` where no input is read by range.
    pub(super) fn fetched(&self) -> Option<(u64, u64)> {
        (!self.0.is_empty()).then(|| {
            self.0
                .iter()
                .map(|r| r.fetched())
                .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
        })
    }
}

/// Whether `p` is a STAC ItemCollection rather than a GeoJSON of curves: a remote `.json`,
/// or a local one whose features carry STAC `assets` (or that says its `stac_version`).
pub(crate) fn is_stac(p: &Path) -> bool {
    let Some(s) = p.to_str() else { return false };
    let lower = s.to_ascii_lowercase();
    if !(lower.ends_with(".json") || lower.ends_with(".geojson")) {
        return false;
    }
    if fractile_remote::is_remote(s) {
        return true;
    }
    let Ok(text) = std::fs::read_to_string(p) else {
        return false;
    };
    serde_json::from_str::<serde_json::Value>(&text).is_ok_and(|j| {
        j.get("stac_version").is_some()
            || j["features"]
                .as_array()
                .and_then(|f| f.first())
                .is_some_and(|f| f["assets"].is_object())
    })
}

/// Whether `p` is a list of locations: a remote `.txt`, or a local one whose every line (but
/// blanks and `#` comments) names a GeoTIFF, a folder or a remote location. Any other text
/// file is an input the encoder does not read, and is told so as such.
fn is_list(p: &Path) -> bool {
    let s = p.to_string_lossy();
    if !s.to_ascii_lowercase().ends_with(".txt") {
        return false;
    }
    if fractile_remote::is_remote(&s) {
        return true;
    }
    let Ok(text) = std::fs::read_to_string(p) else {
        return false;
    };
    let mut lines = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .peekable();
    lines.peek().is_some()
        && lines.all(|l| {
            let lower = l.to_ascii_lowercase();
            fractile_remote::is_remote(l)
                || lower.ends_with(".tif")
                || lower.ends_with(".tiff")
                || l.ends_with('/')
        })
}

/// Whether `inputs` need the opener: a URL, a list, a STAC ItemCollection.
fn by_location(inputs: &[PathBuf]) -> bool {
    inputs
        .iter()
        .any(|p| fractile_remote::is_remote(&p.to_string_lossy()) || is_list(p) || is_stac(p))
}

/// Opens `inputs` as one raster read by bands of rows, on the grid of the GeoTIFF `grid`
/// names if given.
pub(super) fn open(inputs: &[PathBuf], grid: Option<&str>) -> Result<Inputs> {
    if !by_location(inputs) && grid.is_none() {
        let files = fractile_codec::mosaic::input_files(inputs)?;
        let names = files.iter().map(|p| p.display().to_string()).collect();
        if files.len() > 1 && files.iter().all(|f| fractile_codec::rows::is_tiff(f)) {
            let mosaic = Mosaic::open(&files)?;
            return Ok(Inputs {
                names,
                resampled: mosaic.resampled(),
                rows: Box::new(mosaic),
                ranged: Vec::new(),
            });
        }
        let rows = fractile_codec::mosaic::open_rows(inputs)?;
        return Ok(Inputs {
            names,
            rows,
            ranged: Vec::new(),
            resampled: 0,
        });
    }
    let opener = Opener::new().context("starting the reader of remote inputs")?;
    let grid = match grid {
        Some(g) => {
            let (mut tiff, _) = open_headers(&opener, &[g.to_string()])?;
            let georef = tiff.pop().and_then(|t| t.header().georef.clone());
            let Some(georef) = georef else {
                bail!("--grid {g}: a GeoTIFF with a georeference is needed");
            };
            Some((PathBuf::from(g), georef))
        }
        None => None,
    };
    let mut names = Vec::new();
    for p in inputs {
        let s = p.to_string_lossy();
        let listed = opener.list(&s).with_context(|| format!("listing {s}"))?;
        for l in listed {
            // A local folder in a list stays a folder of GeoTIFFs.
            if !fractile_remote::is_remote(&l) && Path::new(&l).is_dir() {
                let files = fractile_codec::mosaic::input_files(&[PathBuf::from(&l)])?;
                names.extend(files.iter().map(|f| f.display().to_string()));
            } else {
                names.push(l);
            }
        }
    }
    if names.is_empty() {
        bail!("the inputs name no raster");
    }
    let (parts, ranged) = open_headers(&opener, &names)?;
    let (rows, resampled): (Box<dyn Rows>, usize) = match parts.len() {
        1 if grid.is_none() => (Box::new(parts.into_iter().next().expect("one part")), 0),
        _ => {
            let mosaic = Mosaic::on(parts, grid)?;
            let resampled = mosaic.resampled();
            (Box::new(mosaic), resampled)
        }
    };
    Ok(Inputs {
        names,
        rows,
        ranged,
        resampled,
    })
}

/// Bytes of remote inputs' chunks an encode keeps once decoded (`KeptBudget`): 256 MiB, so
/// that the rate's sample and the chunks read the same bytes once where they fit, and a
/// part's memory stays bounded whatever its inputs.
const KEPT_BYTES: u64 = 256 << 20;

/// The header a STAC item's grid makes ([`GeoTiff::declared`]), as a GeoTIFF's header says it
/// (`None` for a data type the reader does not take: the file's header is read then).
fn header_of(d: &Declared) -> Option<Header> {
    use fractile_proto::SampleFormat as S;
    // As the reader converts them: integers of up to 16 bits keep their type (a signed byte
    // widens to 16 bits), the rest are read as f32.
    let sample = match d.data_type.as_str() {
        "uint8" => S::U8,
        "uint16" => S::U16,
        "int8" | "int16" => S::I16,
        "int32" | "uint32" | "int64" | "uint64" | "float16" | "float32" | "float64" => S::F32,
        _ => return None,
    };
    let t = d.transform;
    Some(Header {
        width: d.shape[1],
        height: d.shape[0],
        channels: 1,
        kind: fractile_proto::AssetKind::HeightField,
        sample,
        // As a GeoTIFF read says it: metres where georeferenced.
        units: Some("m".into()),
        nodata: d.nodata,
        georef: Some(fractile_proto::Georef {
            epsg: d.epsg,
            origin: [t[2], t[5]],
            pixel_size: [t[0], t[4]],
        }),
        lineage: None,
    })
}

/// An input with its header read, and its ranged file if read by range.
type Opened = (GeoTiff, Option<Arc<RangedFile>>);

/// Each of `names` opened and its header read, a few at a time (thousands of small COGs
/// would otherwise wait on one request after another).
fn open_headers(opener: &Opener, names: &[String]) -> Result<(Vec<GeoTiff>, Vec<Arc<RangedFile>>)> {
    let budget = KeptBudget::new(KEPT_BYTES);
    let open_one = |name: &String| -> Result<Opened> {
        if !fractile_remote::is_remote(name) {
            let tiff = GeoTiff::open_source(TiffSource::File(PathBuf::from(name)))?;
            return Ok((tiff, None));
        }
        let source = opener
            .open(name)
            .with_context(|| format!("opening {name}"))?;
        let file = Arc::new(RangedFile::with_budget(source, budget.clone()));
        let tiff = match opener.declared(name).as_ref().and_then(header_of) {
            // Placed by its STAC item: its header is read when its cells are.
            Some(header) => GeoTiff::declared(TiffSource::Ranged(file.clone()), header),
            None => GeoTiff::open_source(TiffSource::Ranged(file.clone()))?,
        };
        Ok((tiff, Some(file)))
    };
    // Requests in flight: latency-bound, not CPU-bound.
    const AT_ONCE: usize = 32;
    let per = names.len().div_ceil(AT_ONCE).max(1);
    let opened: Vec<Result<Vec<Opened>>> = std::thread::scope(|s| {
        let handles: Vec<_> = names
            .chunks(per)
            .map(|some| s.spawn(move || some.iter().map(open_one).collect::<Result<Vec<_>>>()))
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("a reader panicked")))
            })
            .collect()
    });
    let mut parts = Vec::with_capacity(names.len());
    let mut ranged = Vec::new();
    for batch in opened {
        for (tiff, file) in batch? {
            parts.push(tiff);
            ranged.extend(file);
        }
    }
    Ok((parts, ranged))
}
