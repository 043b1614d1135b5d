//! deploy/k8s agrees with the server: the ConfigMap's `fractile.toml` is a configuration the
//! server loads (an unknown key would stop every replica at start), and its caches and decode
//! budget fit under the Deployment's memory limit with room for the process.

use fractile_server::FileConfig;

fn manifest(name: &str) -> String {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deploy/k8s")
        .join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The block literal under `key: |` in a YAML text, dedented.
fn block(yaml: &str, key: &str) -> String {
    let mut lines = yaml.lines().skip_while(|l| l.trim() != format!("{key}: |"));
    let head = lines.next().expect("the key");
    let indent = head.len() - head.trim_start().len();
    lines
        .take_while(|l| l.trim().is_empty() || l.len() - l.trim_start().len() > indent)
        .map(|l| l.trim_start())
        .collect::<Vec<_>>()
        .join("\n")
}

/// The value after `key:` in the block under `section:` (the first such), in MiB.
fn mib(yaml: &str, section: &str, key: &str) -> u64 {
    let v = yaml
        .lines()
        .skip_while(|l| l.trim() != format!("{section}:"))
        .find_map(|l| l.trim().strip_prefix(&format!("{key}:")))
        .expect("the key")
        .trim()
        .trim_matches('"');
    match v.strip_suffix("Gi") {
        Some(g) => g.parse::<u64>().unwrap() * 1024,
        None => v.strip_suffix("Mi").expect("Mi or Gi").parse().unwrap(),
    }
}

#[test]
fn the_configmap_loads_and_its_memory_fits_the_deployments_limit() {
    let toml = block(&manifest("configmap.yaml"), "fractile.toml");
    let path = std::env::temp_dir().join(format!("fractile-k8s-{}.toml", std::process::id()));
    std::fs::write(&path, &toml).unwrap();
    let config = FileConfig::load(&path).expect("the ConfigMap's fractile.toml loads");
    std::fs::remove_file(&path).unwrap();
    assert_eq!(config.backend.as_deref(), Some("cpu"));
    let held = config.tile_cache_mib.expect("set")
        + config.coarse_cache_mib.expect("set")
        + config.chunk_cache_mib.expect("set")
        + u64::from(config.max_decode_mib.expect("set"));
    let deployment = manifest("deployment.yaml");
    let limit = mib(&deployment, "limits", "memory");
    let request = mib(&deployment, "requests", "memory");
    // The process itself: 68 MB idle (docs/benchmarks.md), with room for allocator slack.
    assert!(
        held + 256 <= limit,
        "{held} MiB of caches and decodes against {limit} MiB"
    );
    assert!(request < limit && request >= 512, "{request} MiB requested");
}
