//! Files in and out: input rasters (images, GeoTIFF and PNG DEMs) and the asset container,
//! which depends on the codecs whose payloads it holds. (Meshes, which the 3D codec itself
//! works on, are [`crate::mesh`].)

pub mod asset;
mod atomic;
pub(crate) mod cache;
pub mod chunked;
mod container;
mod cost;
pub(crate) mod frame;
pub(crate) mod layout;
pub(crate) mod mask;
pub mod mosaic;
pub mod raster;
pub mod rows;
