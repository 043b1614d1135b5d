//! The map under `ChunkCache` (decoded chunks by container, level and index, bounded in
//! their estimated resident bytes): moka's where the `moka` feature is on (the default),
//! quick_cache's elsewhere (the WebAssembly build: moka reads clocks and draws random ids that
//! wasm32-unknown-unknown has not). Generic over the chunk so that it needs no asset type.

use std::sync::Arc;

/// A chunk's key: the container's, its level, its index in the level.
pub(crate) type ChunkKey = (u64, u8, u32);

/// Chunks by key.
#[cfg(feature = "moka")]
pub(crate) type ChunkMap<V> = moka::sync::Cache<ChunkKey, Arc<V>>;
/// Chunks by key, weighed as moka's are.
#[cfg(not(feature = "moka"))]
pub(crate) type ChunkMap<V> = Arc<quick_cache::sync::Cache<ChunkKey, Arc<V>, ChunkWeight<V>>>;

/// Weighs a chunk by its estimated resident bytes (quick_cache's weigher).
#[cfg(not(feature = "moka"))]
pub(crate) struct ChunkWeight<V>(pub(crate) fn(&V) -> u64);

#[cfg(not(feature = "moka"))]
impl<V> Clone for ChunkWeight<V> {
    fn clone(&self) -> Self {
        ChunkWeight(self.0)
    }
}

#[cfg(not(feature = "moka"))]
impl<V> quick_cache::Weighter<ChunkKey, Arc<V>> for ChunkWeight<V> {
    fn weight(&self, _: &ChunkKey, v: &Arc<V>) -> u64 {
        (self.0)(v).max(1)
    }
}

/// A map of at most `bytes`, each chunk weighing `weight` of it.
pub(crate) fn chunk_map<V: Send + Sync + 'static>(
    bytes: u64,
    weight: fn(&V) -> u64,
) -> ChunkMap<V> {
    #[cfg(feature = "moka")]
    return moka::sync::Cache::builder()
        .max_capacity(bytes)
        .weigher(move |_, v: &Arc<V>| weight(v).min(u64::from(u32::MAX)) as u32)
        .build();
    #[cfg(not(feature = "moka"))]
    return Arc::new(quick_cache::sync::Cache::with_weighter(
        64,
        bytes,
        ChunkWeight(weight),
    ));
}
