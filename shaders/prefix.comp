#version 450
// Prefiltering's basis computation and per-band prefix sums (core/src/prefiltered.rs,
// basis_kernels.rs): per band, a running sum of weighted basis-table rows, each output
// row scaled to a weighted mean and stored as f32 or 16-bit snorm. One workgroup per
// band, one invocation per pair of lanes; sums run in the CPU's order, uncontracted.

layout(local_size_x = 32) in;

layout(push_constant) uniform Push {
    uint stride;     // values per row, even
    uint snorm;      // 1: 16-bit snorm pairs packed per uint, 0: f32 bits
    uint band_count;
    uint unused;
} pc;

layout(std430, binding = 0) readonly buffer Bands { uvec2 bands[]; }; // (first row, rows)
layout(std430, binding = 1) readonly buffer Entries { uint entries[]; };
layout(std430, binding = 2) readonly buffer Weights { float weights[]; };
layout(std430, binding = 3) readonly buffer Scales { float scales[]; };
// Rows of the basis table in pairs of lanes (rows hold an even number of values).
layout(std430, binding = 4) readonly buffer Table { vec2 table2[]; };
layout(std430, binding = 5) writeonly buffer Basis { uint basis[]; };

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

void main() {
    uint band = gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x;
    uint pair = gl_LocalInvocationID.x;
    if (band >= pc.band_count || 2u * pair >= pc.stride) {
        return;
    }
    uvec2 b = bands[band];
    uint first_row = b.x;
    uint samples = b.y - 1u;
    uint offset = first_row - band;
    uint pairs = pc.stride / 2u;
    store(first_row, pair, 0.0, 0.0);
    precise vec2 sum = vec2(0.0);
    // Four samples at a time: their loads are independent of the running sum, so they are
    // issued together; the sum itself runs sample by sample, as on the CPU.
    uint i = 0u;
    for (; i + 4u <= samples; i += 4u) {
        uint k = offset + i;
        uvec4 entry = uvec4(entries[k], entries[k + 1u], entries[k + 2u], entries[k + 3u]);
        vec4 w = vec4(weights[k], weights[k + 1u], weights[k + 2u], weights[k + 3u]);
        vec4 scale = vec4(scales[k], scales[k + 1u], scales[k + 2u], scales[k + 3u]);
        vec2 t[4] = vec2[4](table2[entry.x * pairs + pair], table2[entry.y * pairs + pair],
                            table2[entry.z * pairs + pair], table2[entry.w * pairs + pair]);
        for (uint j = 0u; j < 4u; ++j) {
            precise vec2 added = w[j] * t[j];
            sum = sum + added;
            precise vec2 value = sum * scale[j];
            store(first_row + 1u + i + j, pair, value.x, value.y);
        }
    }
    for (; i < samples; ++i) {
        uint k = offset + i;
        precise vec2 added = weights[k] * table2[entries[k] * pairs + pair];
        sum = sum + added;
        precise vec2 value = sum * scales[k];
        store(first_row + 1u + i, pair, value.x, value.y);
    }
}
