//! The maps under `ChunkCache` (decoded chunks by container, level and index) and
//! `extract::CoarseGrids` (coarse decodes by asset and size), bounded in their estimated
//! resident bytes: moka's where the `moka` feature is on (the default), quick_cache's elsewhere
//! (the WebAssembly build: moka reads clocks and draws random ids that wasm32-unknown-unknown
//! has not). Generic over key and value so that it needs no asset type.

use std::hash::Hash;
use std::sync::Arc;

/// A chunk's key: the container's, its level, its index in the level.
pub(crate) type ChunkKey = (u64, u8, u32);

/// Values by key, bounded in bytes.
#[cfg(feature = "moka")]
pub(crate) type KeyedMap<K, V> = moka::sync::Cache<K, Arc<V>>;
/// Values by key, weighed as moka's are.
#[cfg(not(feature = "moka"))]
pub(crate) type KeyedMap<K, V> = Arc<quick_cache::sync::Cache<K, Arc<V>, Weight<V>>>;

/// Chunks by key.
pub(crate) type ChunkMap<V> = KeyedMap<ChunkKey, V>;

/// Weighs a value by its estimated resident bytes (quick_cache's weigher).
#[cfg(not(feature = "moka"))]
pub(crate) struct Weight<V>(pub(crate) fn(&V) -> u64);

#[cfg(not(feature = "moka"))]
impl<V> Clone for Weight<V> {
    fn clone(&self) -> Self {
        Weight(self.0)
    }
}

#[cfg(not(feature = "moka"))]
impl<K, V> quick_cache::Weighter<K, Arc<V>> for Weight<V> {
    fn weight(&self, _: &K, v: &Arc<V>) -> u64 {
        (self.0)(v).max(1)
    }
}

/// A map of at most `bytes`, each value weighing `weight` of it.
pub(crate) fn keyed_map<K, V>(bytes: u64, weight: fn(&V) -> u64) -> KeyedMap<K, V>
where
    K: Hash + Eq + Clone + Send + Sync + 'static,
    V: Send + Sync + 'static,
{
    #[cfg(feature = "moka")]
    return moka::sync::Cache::builder()
        .max_capacity(bytes)
        .weigher(move |_, v: &Arc<V>| weight(v).min(u64::from(u32::MAX)) as u32)
        .build();
    #[cfg(not(feature = "moka"))]
    return Arc::new(quick_cache::sync::Cache::with_weighter(
        64,
        bytes,
        Weight(weight),
    ));
}

/// The value under `key`, made by `make` where there is none; callers that ask for one key
/// at once wait for one `make` (both caches coalesce them).
pub(crate) fn get_or_make<K, V>(
    map: &KeyedMap<K, V>,
    key: K,
    make: impl FnOnce() -> Arc<V>,
) -> Arc<V>
where
    K: Hash + Eq + Clone + Send + Sync + 'static,
    V: Send + Sync + 'static,
{
    #[cfg(feature = "moka")]
    return map.get_with(key, make);
    #[cfg(not(feature = "moka"))]
    return map
        .get_or_insert_with(&key, || Ok::<_, std::convert::Infallible>(make()))
        .unwrap_or_else(|never| match never {});
}
