#version 450
#extension GL_GOOGLE_include_directive : require
// The rectified map's uniformity table (core/src/uniformity.rs): per slice, the lowest
// and highest K over each block of BLOCK samples (each sample over its whole interval,
// EpipolarMap::sample_bounds), then over runs of 2^k blocks. One workgroup per slice;
// each level reads only the one below, written by the same workgroup.

layout(local_size_x = 64) in;

layout(push_constant) uniform Push {
    uint slices;
    uint samples;
    uint reciprocal;  // the layout's K scales with 1/s (EpipolarMap::sample_bounds)
} pc;

layout(std430, binding = 0) readonly buffer Rectified { float rectified[]; };
// Per sample index: (near, far) factors, shared by every slice.
layout(std430, binding = 1) readonly buffer BoundFactors { vec2 bound_factors[]; };
layout(std430, binding = 2) buffer Runs { vec2 runs[]; };

#include "common.glsl"

const uint BLOCK = 16u;

void main() {
    uint slice = gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x;
    if (slice >= pc.slices) {
        return;
    }
    uint blocks = (pc.samples + BLOCK - 1u) / BLOCK;
    uint levels = findMSB(blocks) + 1u;
    uint table = slice * levels * blocks;
    uint row = slice * pc.samples;
    for (uint b = gl_LocalInvocationID.x; b < blocks; b += gl_WorkGroupSize.x) {
        vec2 bounds = vec2(uintBitsToFloat(0x7f800000u), uintBitsToFloat(0xff800000u));
        for (uint i = b * BLOCK; i < min((b + 1u) * BLOCK, pc.samples); ++i) {
            vec2 s = sample_bounds_from(bound_factors[i], rectified[row + i], pc.reciprocal != 0u);
            bounds = vec2(min(bounds.x, s.x), max(bounds.y, s.y));
        }
        runs[table + b] = bounds;
    }
    for (uint k = 1u; k < levels; ++k) {
        memoryBarrierBuffer();
        barrier();
        uint half_ = 1u << (k - 1u);
        uint below = table + (k - 1u) * blocks;
        uint level = table + k * blocks;
        for (uint b = gl_LocalInvocationID.x; b + (1u << k) <= blocks; b += gl_WorkGroupSize.x) {
            vec2 x = runs[below + b];
            vec2 y = runs[below + b + half_];
            runs[level + b] = vec2(min(x.x, y.x), max(x.y, y.y));
        }
    }
}
