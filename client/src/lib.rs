//! The fractile client. The HTTP client and progressive refinement arrive with issue 4; until then
//! this crate only re-exports the wire types it will speak, so that its users can depend on it.
pub use fractile_proto as proto;
