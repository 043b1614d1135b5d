//! A real fractile server for end-to-end tests: assets encoded from the repo's test data, served
//! over TCP on an ephemeral loopback port by its own runtime on its own thread, shared by every
//! test of the process (each test brings its own runtime, which a server must outlive).

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use fractile_server::AppState;
use fractile_server::Store;

/// The write token of the test server.
pub const TOKEN: &str = "e2e-secret";

/// Most points per batch on the test server (small, so that an over-limit batch is cheap).
pub const MAX_POINTS: usize = 5000;

/// Most iterations on the test server: room for 100-step references.
pub const MAX_ITERATIONS: u32 = 128;

/// A file of the repo's test data.
pub fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// Encodes a test-data file as the demo server would.
pub fn encode_file(name: &str, bpp: f64) -> Vec<u8> {
    let r = Raster::open(&data(name)).expect("test data reads");
    let mut s = QuadtreeSettings {
        rate: RateMode::TargetBpp(bpp),
        ..QuadtreeSettings::default()
    };
    s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
    encode(&r, &s, &|_, _| {}).expect("test data encodes").bytes
}

/// Base URL of the shared test server (started on first use) with assets `jacksboro` (a
/// georeferenced DEM) and `camera` (a grey image).
pub fn server() -> String {
    static BASE: OnceLock<String> = OnceLock::new();
    BASE.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("fractile-e2e-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        for (id, file, bpp) in [
            ("jacksboro", "jacksboro.tif", 1.6),
            ("camera", "camera.png", 0.48),
        ] {
            std::fs::write(dir.join(format!("{id}.fra")), encode_file(file, bpp)).expect("write");
        }
        // A volume (IFS3D) of a real mesh, as `fractile encode fandisk.off --grid 48` makes it.
        let mesh = fractile_codec::mesh::Mesh::read(&data("mesh/fandisk.off")).expect("mesh");
        let s = fractile_codec::encode::volume::MeshSettings {
            grid: 48,
            ..Default::default()
        };
        let vol =
            fractile_codec::encode::volume::encode_mesh(&mesh, &s, "fandisk.off").expect("encode");
        std::fs::write(dir.join("fandisk.fra"), &vol.bytes).expect("write");
        let (store, _) = Store::open(&dir).expect("store opens");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .expect("runtime");
            rt.block_on(async move {
                let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
                    .await
                    .expect("bind");
                let base = format!("http://{}", listener.local_addr().expect("addr"));
                let mut state = AppState::new(store, base.clone());
                state.writes = fractile_server::Writes::Token(TOKEN.into());
                state.limits.max_points = MAX_POINTS;
                state.limits.max_iterations = MAX_ITERATIONS;
                state.max_upload = 4 * 1024 * 1024;
                tx.send(base).expect("send");
                let app = fractile_server::app(Arc::new(state));
                axum::serve(listener, app).await.expect("server runs");
            });
        });
        rx.recv().expect("server starts")
    })
    .clone()
}
