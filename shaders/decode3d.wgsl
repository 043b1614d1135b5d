// Continuous decoding of a 3D octree operator (codec::codecs::ifs3d::octree, IFS3D), one invocation per point.
// Mirrors OctreeOperator::step and decode::points line by line, in f32:
//   cell = min(u32(max(p * inv_cell, 0)), side - 1) per axis; c = lut[(z * side + y) * side + x]
//   phi_a(p) = coef_a * p[perm_a] + c_a, g = offset, s = contrast
//   value = sum_k g_k prod_{j<k} s_j + seed prod s, bound = |prod s| * half
// Points come from a list (mode 0: x, y, z unit coordinates) or a box grid (mode 1): grid point
// (i, j, k) at (xs[i], ys[j], zs[k]), the axes the host sends (decode::volume_axes, what
// decode::volume_window samples), so that both decode the same points.
// Unit coordinates are clamped to [0, 1] as the CPU clamps them.

struct Params {
    count: u32,
    first: u32,
    iterations: u32,
    mode: u32,
    tolerance: f32,
    seed: f32,
    half: f32,
    side: u32,
    inv_cell: f32,
    valid: f32,
    nx: u32,
    ny: u32,
    nz: u32,
    row: u32,
    // The fixed-point step of positions and its inverse (codec::core::decode::to_frame).
    quantum: f32,
    inv_quantum: f32,
    // 1: write `values` and `summary` instead of `results` (as in decode2d.wgsl).
    values_only: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> lut: array<u32>;
// Three vec4 per range: (c.xyz, contrast), (coef.xyz, offset), (perm.xyz as u32 bits, 0).
@group(0) @binding(2) var<storage, read> cells: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> points: array<f32>;
// Bindings 4 to 6, the outputs, and the entry point `main`: shaders/entry.wgsl.

fn unit_point(k: u32) -> vec3<f32> {
    if (params.mode == 0u) {
        return vec3<f32>(points[3u * k], points[3u * k + 1u], points[3u * k + 2u]);
    }
    let i = k % params.nx;
    let j = (k / params.nx) % params.ny;
    let l = k / (params.nx * params.ny);
    return vec3<f32>(points[i], points[params.nx + j], points[params.nx + params.ny + l]);
}

// Value, bound, steps taken and 1 for point k of the dispatch's list or box.
fn decode(k: u32) -> vec4<f32> {
    let unit = clamp(unit_point(k), vec3<f32>(0.0), vec3<f32>(1.0));
    var p = floor(unit * params.valid * params.inv_quantum + vec3<f32>(0.5)) * params.quantum;
    var acc_g = 0.0;
    var acc_s = 1.0;
    var taken = 0u;
    let last = params.side - 1u;
    for (var n = 0u; n < params.iterations; n = n + 1u) {
        if (acc_s == 0.0 || abs(acc_s) * params.half <= params.tolerance) {
            break;
        }
        let cx = min(u32(max(p.x * params.inv_cell, 0.0)), last);
        let cy = min(u32(max(p.y * params.inv_cell, 0.0)), last);
        let cz = min(u32(max(p.z * params.inv_cell, 0.0)), last);
        let c = lut[(cz * params.side + cy) * params.side + cx];
        let a = cells[3u * c];
        let b = cells[3u * c + 1u];
        let perm = bitcast<vec4<u32>>(cells[3u * c + 2u]);
        acc_g = acc_g + acc_s * b.w;
        acc_s = acc_s * a.w;
        taken = taken + 1u;
        p = vec3<f32>(
            b.x * p[perm.x] + a.x,
            b.y * p[perm.y] + a.y,
            b.z * p[perm.z] + a.z,
        );
    }
    return vec4<f32>(acc_g + acc_s * params.seed, abs(acc_s) * params.half, f32(taken), 1.0);
}
