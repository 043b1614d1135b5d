//! Wire types of fractile: what travels in asset files and, later, over HTTP.
//!
//! Everything here is plain data with serde derives. The binary encoding lives in [`wire`] alone,
//! so the serializer (bincode 2.0 today, see its note) can be swapped by editing one file.

pub mod asset;
pub mod catalog;
pub mod curve;
pub mod heights;
pub mod points;
pub mod query;
pub mod subtree;
pub mod tiles;
pub mod wire;

pub use asset::*;
pub use catalog::*;
pub use curve::*;
pub use points::*;
pub use wire::{WireError, decode, encode};
