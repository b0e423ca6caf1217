#version 450
// Prefiltering's basis computation and per-band prefix sums (core/src/prefiltered.rs,
// basis_kernels.rs): per band, a running sum of weighted basis-table rows, a fixed number
// of samples per output row, each output row scaled to a weighted mean and stored as f32
// or 16-bit snorm. One workgroup per band. Its rows are cut into `runs_per_band` runs, one
// invocation per run and pair of lanes: each sums its run, the runs before it give its
// starting sum, and it sums its run again storing every row. A band is one serial chain
// on the CPU; here the chain is a run long, so a few hundred bands of a thousand rows keep
// the device busy. Each run sums in the CPU's order, uncontracted.

layout(local_size_x = 256) in;

layout(push_constant) uniform Push {
    uint stride;     // values per row, even
    uint snorm;      // 1: 16-bit snorm pairs packed per uint, 0: f32 bits
    uint band_count;
    uint samples_per_row;
    uint runs_per_band;  // at most the workgroup's size over stride / 2
} pc;

layout(std430, binding = 0) readonly buffer Bands { uvec2 bands[]; }; // (first row, rows)
layout(std430, binding = 1) readonly buffer Entries { uint entries[]; };   // per sample
layout(std430, binding = 2) readonly buffer Weights { float weights[]; };  // per sample
layout(std430, binding = 3) readonly buffer Scales { float scales[]; };    // per row
// Rows of the basis table in pairs of lanes (rows hold an even number of values).
layout(std430, binding = 4) readonly buffer Table { vec2 table2[]; };
layout(std430, binding = 5) writeonly buffer Basis { uint basis[]; };

// Each run's sum, per pair of lanes: run c's at c · stride / 2 + pair.
shared vec2 run_sums[256];

// Round half away from zero after clamping to ±1, as BasisValue::store for i16.
uint snorm16(float value) {
    precise float scaled = clamp(value * 32767.0, -32767.0, 32767.0);
    precise float shifted = scaled + (scaled >= 0.0 ? 0.5 : -0.5);
    return uint(int(shifted)) & 0xFFFFu;
}

void store(uint row, uint pair, float v0, float v1) {
    if (pc.snorm != 0u) {
        basis[row * (pc.stride / 2u) + pair] = snorm16(v0) | (snorm16(v1) << 16);
    } else {
        uint at = row * pc.stride + 2u * pair;
        basis[at] = floatBitsToUint(v0);
        basis[at + 1u] = floatBitsToUint(v1);
    }
}

// `sum` plus sample row k's weighted table rows, in order.
vec2 add_row(vec2 sum, uint k, uint pair, uint pairs) {
    uint per_row = pc.samples_per_row;
    uint first = k * per_row;
    uint j = 0u;
    // Two samples at a time: their loads are independent of the running sum, so they are
    // issued together; the sum itself runs sample by sample, as on the CPU.
    for (; j + 2u <= per_row; j += 2u) {
        uvec2 entry = uvec2(entries[first + j], entries[first + j + 1u]);
        vec2 w = vec2(weights[first + j], weights[first + j + 1u]);
        vec2 t0 = table2[entry.x * pairs + pair];
        vec2 t1 = table2[entry.y * pairs + pair];
        precise vec2 added0 = w.x * t0;
        sum = sum + added0;
        precise vec2 added1 = w.y * t1;
        sum = sum + added1;
    }
    for (; j < per_row; ++j) {
        precise vec2 added = weights[first + j] * table2[entries[first + j] * pairs + pair];
        sum = sum + added;
    }
    return sum;
}

void main() {
    uint band = gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x;
    if (band >= pc.band_count) {
        return;  // the whole workgroup: the barrier below is still reached by all or none
    }
    uint pairs = pc.stride / 2u;
    uint pair = gl_LocalInvocationID.x % pairs;
    uint run = gl_LocalInvocationID.x / pairs;
    bool summing = run < pc.runs_per_band;
    uvec2 b = bands[band];
    uint first_row = b.x;
    uint rows = b.y - 1u;
    uint offset = first_row - band;
    uint per_run = (rows + pc.runs_per_band - 1u) / pc.runs_per_band;
    // Invocations past the last run get begin = end = rows.
    uint begin = min(run * per_run, rows);
    uint end = min(begin + per_run, rows);
    precise vec2 own = vec2(0.0);
    for (uint i = begin; i < end; ++i) {
        own = add_row(own, offset + i, pair, pairs);
    }
    run_sums[gl_LocalInvocationID.x] = own;
    barrier();
    if (!summing) {
        return;
    }
    precise vec2 sum = vec2(0.0);
    for (uint c = 0u; c < run; ++c) {
        sum = sum + run_sums[c * pairs + pair];
    }
    if (run == 0u) {
        store(first_row, pair, 0.0, 0.0);
    }
    for (uint i = begin; i < end; ++i) {
        sum = add_row(sum, offset + i, pair, pairs);
        precise vec2 value = sum * scales[offset + i];
        store(first_row + 1u + i, pair, value.x, value.y);
    }
}
