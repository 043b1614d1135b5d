//! Files in and out: input rasters (images, GeoTIFF and PNG DEMs) and the asset container,
//! which depends on the codecs whose payloads it holds. (Meshes, which the 3D codec itself
//! works on, are [`crate::mesh`].)

pub(crate) mod asset;
mod atomic;
pub(crate) mod cache;
pub(crate) mod chunked;
mod container;
mod cost;
pub(crate) mod frame;
pub(crate) mod layout;
pub(crate) mod mask;
pub(crate) mod mosaic;
pub(crate) mod ranged;
pub(crate) mod raster;
pub(crate) mod resample;
pub(crate) mod rows;
