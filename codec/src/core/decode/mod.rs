//! Decoding a partitioned affine operator, three ways, for any [`crate::core::operator::Operator`].
//!
//! * [`discrete`]: iterate W on a grid of any size. The previous iterate is averaged over the
//!   domain footprint of each output pixel (a box of `expansion` output pixels, sampled
//!   bilinearly) — exactly what the encoder fitted at the native size, and the seed's decoder.
//! * [`point`]: the value at one real point by inverse iteration (seed Fig. 5): follow phi n times,
//!   then `value = seed * prod(s) + sum_k g_k prod_{j<k} s_j`, with the a-priori bound
//!   `prod |s_k| * max |seed - f|`. This *samples* the attractor of the point operator; discrete
//!   decoding *averages*. On smooth content the two agree closely; at sharp edges they differ by
//!   up to the local contrast, and the point form has more fine detail at deep zoom
//!   (the bench measures the difference).
//! * [`window`]: a rectangle at any resolution, answered by whichever of the two is cheaper.
//!
//! By concern: `continuous` (points, chains, separable grids), `patch` (bilinear patches in
//! f64), `discrete` (iterating W on a grid; windows).

mod continuous;
mod discrete;
mod patch;

pub use continuous::*;
pub use discrete::*;
pub use patch::*;

#[cfg(test)]
mod tests;
