// Continuous decoding of a flattened 2D operator (codec::core::pieces), one invocation per point.
// Mirrors PieceTable::step and decode::points line by line, in f32:
//   p = floor(unit * valid / quantum + 0.5) * quantum (fixed-point starts, see below)
//   cell = clamp(floor((p - lut_origin) * inv_lut_cell), 0, size - 1); entry = lut[cell]
//   piece = entry & 0x7fffffff (+1 on the far half of a split cell, u + v > 1)
//   (u, v) = clamp((p - origin) * inv_size, 0, 1)
//   g, s bilinear in (u, v); phi(p) = n0 + nu u + nv v per axis
//   value = sum_k g_k prod_{j<k} s_j + seed prod s, bound = |prod s| * half
// A table that is a lattice (codec::core::pieces::Lattice, the projected codec's) comes as
// its offsets alone, a cell's coefficients or (BLOCKS) the corner values that blocks of 2 x 2
// cells share: the piece is the cell, its origin the cell's, one contrast, phi's x by column
// and y by row (Lattice::step). A lattice whose chains end on its samples
// (codec::core::pieces::Ends, the projected codec's) stops a chain once |prod s| times its cell's
// residual bound is within the tolerance and answers acc_g + acc_s S(p), S the bilinear
// interpolant of the samples, within |acc_s| R(p) plus its rounding (ProjectedOperator::
// run_chains and end_chain), instead of the seed within |acc_s| half.
// Points come from a list (mode 0), a regular grid over a unit-square window (mode 1), or a
// separable grid (mode 2: the pixels of a Web Mercator tile over a lon/lat-placed asset, whose
// unit x depends on the column only and unit y on the row only). For mode 2 the host sends the
// two axes (width + height floats, computed in f64): the chains that follow expand position
// errors by the domain/range ratio at every step, and an f32 reprojection here (sinh, atan, and
// an offset of hundreds cancelling to a unit coordinate) starts them a few thousandths of a
// source pixel off, enough to end ten steps later in other ranges than the CPU's.

struct Params {
    // Number of points in this dispatch and the first point's index (chunked dispatches).
    count: u32,
    first: u32,
    iterations: u32,
    mode: u32,
    tolerance: f32,
    seed: f32,
    half: f32,
    width: u32,          // grid width in points (modes 1 and 2)
    lut_origin: vec2<f32>,
    lut_cell: vec2<f32>,
    lut_size: vec2<u32>,
    valid: vec2<f32>,
    // Mode 1: unit point of grid point (i, j) = a + (i + 0.5, j + 0.5) * b.
    a: vec2<f32>,
    b: vec2<f32>,
    // Points per row of the dispatch grid (x groups * 256), for 2D dispatches past 65,535 groups.
    row: u32,
    // The fixed-point step of positions (a power of two) and its inverse.
    quantum: f32,
    inv_quantum: f32,
    // 1: write `values` and `summary` instead of `results`.
    values_only: u32,
    // 1 / lut_cell: a product is exact for power-of-two cells; a WGSL division need not be.
    inv_lut_cell: vec2<f32>,
    _pad1: u32,
    _pad2: u32,
    // A lattice's one contrast.
    contrast: vec4<f32>,
    // Samples along x and y of a lattice whose chains end on them; their rounding a step.
    ends_size: vec2<u32>,
    ulps: f32,
    _pad3: u32,
};

// The tables are a lattice (codec::core::pieces::Lattice): `pieces` holds each cell's offset,
// `lut` the maps of the columns then of the rows (vec4 as u32 bits), `contrast` the one
// contrast. A pipeline constant, not a uniform: each pipeline then has its own loop (a branch
// on a uniform cost 40% of the kernel's time on lavapipe).
override LATTICE: bool = false;
// The lattice's offsets are in blocks of 2 x 2 cells (codec::core::pieces::Offsets::Blocks):
// `pieces` holds, as consecutive floats, each block's values at its 3 x 3 corners, and a
// cell's coefficients are computed from its four as `bilinear` does.
override BLOCKS: bool = false;
// The lattice's chains end on its samples: `lut` holds, after the maps, the samples and then
// each cell's residual bound (f32 as u32 bits).
override ENDS: bool = false;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> lut: array<u32>;
@group(0) @binding(2) var<storage, read> pieces: array<vec4<f32>>;
// Mode 0: x0, y0, x1, y1, ...; mode 2: the width unit xs, then the height unit ys.
@group(0) @binding(3) var<storage, read> points: array<f32>;
// Bindings 4 to 6, the outputs, and the entry point `main`: shaders/entry.wgsl.

const SPLIT: u32 = 0x80000000u;

fn lut_vec4(k: u32) -> vec4<f32> {
    return bitcast<vec4<f32>>(vec4<u32>(lut[4u * k], lut[4u * k + 1u], lut[4u * k + 2u], lut[4u * k + 3u]));
}

// Value n of a lattice's blocks of offsets, which `pieces` holds as consecutive floats.
fn block_value(n: u32) -> f32 {
    return pieces[n / 4u][n % 4u];
}

fn unit_point(k: u32) -> vec2<f32> {
    if (params.mode == 0u) {
        return vec2<f32>(points[2u * k], points[2u * k + 1u]);
    }
    let i = k % params.width;
    let j = k / params.width;
    if (params.mode == 2u) {
        return vec2<f32>(points[i], points[params.width + j]);
    }
    let ij = vec2<f32>(f32(i), f32(j)) + vec2<f32>(0.5, 0.5);
    return params.a + ij * params.b;
}

// The cell between samples of frame coordinate t on an axis of n samples (at k + 0.5), and the
// position in it (ProjectedOperator::locate).
fn locate(t: f32, n: u32) -> vec2<f32> {
    let s = clamp(t - 0.5, 0.0, f32(n - 1u));
    let c = min(u32(s), n - 2u);
    return vec2<f32>(f32(c), s - f32(c));
}

fn ends_sample(x: u32, y: u32) -> f32 {
    let base = 4u * (params.lut_size.x + params.lut_size.y);
    return bitcast<f32>(lut[base + y * params.ends_size.x + x]);
}

// R(p): the residual bound of p's cell.
fn residual_at(p: vec2<f32>) -> f32 {
    let n = params.ends_size;
    let i = u32(locate(p.x, n.x).x);
    let j = u32(locate(p.y, n.y).x);
    let base = 4u * (params.lut_size.x + params.lut_size.y) + n.x * n.y;
    return bitcast<f32>(lut[base + j * (n.x - 1u) + i]);
}

// S(p): the bilinear interpolant of the samples (ProjectedOperator::bilinear).
fn interpolant(p: vec2<f32>) -> f32 {
    let lx = locate(p.x, params.ends_size.x);
    let ly = locate(p.y, params.ends_size.y);
    let i = u32(lx.x);
    let j = u32(ly.x);
    let r0 = ends_sample(i, j);
    let top = r0 + (ends_sample(i + 1u, j) - r0) * lx.y;
    let r1 = ends_sample(i, j + 1u);
    let bottom = r1 + (ends_sample(i + 1u, j + 1u) - r1) * lx.y;
    return top + (bottom - top) * ly.y;
}

// Value, bound, steps taken and 1 for point k of the dispatch's grid or list.
fn decode(k: u32) -> vec4<f32> {
    let unit = unit_point(k);
    // Outside the unit square: no value (NaN), as the CPU answers outside points.
    if (unit.x < 0.0 || unit.x > 1.0 || unit.y < 0.0 || unit.y > 1.0 || unit.x != unit.x) {
        let nan = bitcast<f32>(0x7fc00000u);
        return vec4<f32>(nan, 0.0, 0.0, 0.0);
    }
    // Positions are multiples of the quantum, small enough that every step below is exact in
    // f32 on the lattice codecs (codec::core::decode::to_frame and position_quantum): the
    // same bits as the CPU's chains, so both visit the same cells.
    var p = floor(unit * params.valid * params.inv_quantum + vec2<f32>(0.5)) * params.quantum;
    var acc_g = 0.0;
    var acc_s = 1.0;
    var taken = 0u;
    for (var n = 0u; n < params.iterations; n = n + 1u) {
        // operator::active, whose bound is the cell's residual where chains end on samples.
        var reach = params.half;
        if (ENDS) {
            reach = residual_at(p);
        }
        if (!(acc_s != 0.0 && abs(acc_s) * reach > params.tolerance)) {
            break;
        }
        // PieceTable::step's lookups (Lattice::step's for a lattice).
        let cf = floor((p - params.lut_origin) * params.inv_lut_cell);
        let cx = min(u32(max(cf.x, 0.0)), params.lut_size.x - 1u);
        let cy = min(u32(max(cf.y, 0.0)), params.lut_size.y - 1u);
        var uv: vec2<f32>;
        var g: vec4<f32>;
        var s: vec4<f32>;
        var nx: vec4<f32>;
        var ny: vec4<f32>;
        if (LATTICE) {
            // The cell's origin: exact, the cell being a power of two.
            let origin = params.lut_origin + vec2<f32>(f32(cx), f32(cy)) * params.lut_cell;
            uv = clamp((p - origin) * params.inv_lut_cell, vec2<f32>(0.0), vec2<f32>(1.0));
            if (BLOCKS) {
                let n = 9u * ((cy / 2u) * (params.lut_size.x / 2u) + cx / 2u) + 3u * (cy % 2u) + cx % 2u;
                let c00 = block_value(n);
                let c10 = block_value(n + 1u);
                let c01 = block_value(n + 3u);
                let c11 = block_value(n + 4u);
                // pieces::bilinear, in its order of operations.
                g = vec4<f32>(c00, c10 - c00, c01 - c00, c00 - c10 - c01 + c11);
            } else {
                g = pieces[cy * params.lut_size.x + cx];
            }
            s = params.contrast;
            nx = lut_vec4(cx);
            ny = lut_vec4(params.lut_size.x + cy);
        } else {
            let entry = lut[cy * params.lut_size.x + cx];
            var piece = entry & 0x7fffffffu;
            let head = pieces[piece * 5u];
            uv = clamp((p - head.xy) * head.zw, vec2<f32>(0.0), vec2<f32>(1.0));
            if ((entry & SPLIT) != 0u && uv.x + uv.y > 1.0) {
                piece = piece + 1u;
            }
            g = pieces[piece * 5u + 1u];
            s = pieces[piece * 5u + 2u];
            nx = pieces[piece * 5u + 3u];
            ny = pieces[piece * 5u + 4u];
        }
        let u = uv.x;
        let v = uv.y;
        let offset = g.x + g.y * u + g.z * v + g.w * u * v;
        let contrast = s.x + s.y * u + s.z * v + s.w * u * v;
        acc_g = acc_g + acc_s * offset;
        acc_s = acc_s * contrast;
        taken = taken + 1u;
        p = vec2<f32>(nx.x + nx.y * u + nx.z * v, ny.x + ny.y * u + ny.z * v);
    }
    if (ENDS) {
        let bound = abs(acc_s) * residual_at(p) + f32(taken + 4u) * params.ulps;
        return vec4<f32>(acc_g + acc_s * interpolant(p), bound, f32(taken), 1.0);
    }
    return vec4<f32>(acc_g + acc_s * params.seed, abs(acc_s) * params.half, f32(taken), 1.0);
}
