// The entry point both kernels share, appended to each by fractile-gpu: it decodes point
// `first + idx` with the kernel's own `decode` (value, bound, steps taken, 1) and writes the
// four floats to `results`, or, in a values-only dispatch, the value to `values` and the
// largest bound and step count to `summary`. The kernel's `Params` has `count`, `first`,
// `row` (points a row of the dispatch grid, for 2D dispatches past 65,535 groups) and
// `values_only`.

@group(0) @binding(4) var<storage, read_write> results: array<vec4<f32>>;
// Values-only dispatches: the values, and the largest bound's bits and step count.
@group(0) @binding(5) var<storage, read_write> values: array<f32>;
@group(0) @binding(6) var<storage, read_write> summary: array<atomic<u32>>;

// The largest bound and step count of a workgroup's points (values-only dispatches), before
// one invocation folds them into `summary`: one global atomic a workgroup, not one a point.
var<workgroup> group_bound: atomic<u32>;
var<workgroup> group_taken: atomic<u32>;

@compute @workgroup_size(256)
fn main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let idx = id.x + id.y * params.row;
    let live = idx < params.count;
    var r = vec4<f32>(0.0);
    if (live) {
        r = decode(params.first + idx);
    }
    if (params.values_only == 0u) {
        if (live) {
            results[idx] = r;
        }
        return;
    }
    // Values alone (4 bytes a point to read back) and the bounds reduced here: a bound is a
    // non-negative float, whose bits order as unsigned integers do.
    if (lane == 0u) {
        atomicStore(&group_bound, 0u);
        atomicStore(&group_taken, 0u);
    }
    workgroupBarrier();
    if (live) {
        values[idx] = r.x;
        atomicMax(&group_bound, bitcast<u32>(r.y));
        atomicMax(&group_taken, u32(r.z));
    }
    workgroupBarrier();
    if (lane == 0u) {
        atomicMax(&summary[0], atomicLoad(&group_bound));
        atomicMax(&summary[1], atomicLoad(&group_taken));
    }
}
