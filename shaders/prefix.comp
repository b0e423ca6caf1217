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
layout(std430, binding = 4) readonly buffer Table { float table[]; };
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
    uint lane = 2u * pair;
    store(first_row, pair, 0.0, 0.0);
    precise float s0 = 0.0;
    precise float s1 = 0.0;
    for (uint i = 0u; i < samples; ++i) {
        uint k = offset + i;
        uint entry = entries[k];
        float w = weights[k];
        float scale = scales[k];
        precise float a0 = w * table[entry * pc.stride + lane];
        precise float a1 = w * table[entry * pc.stride + lane + 1u];
        s0 = s0 + a0;
        s1 = s1 + a1;
        precise float v0 = s0 * scale;
        precise float v1 = s1 * scale;
        store(first_row + 1u + i, pair, v0, v1);
    }
}
