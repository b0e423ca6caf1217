#version 450
#extension GL_GOOGLE_include_directive : require
// Adaptive shading's dark floor (core/src/adaptive.rs: DARK_SHARE): a share of the coarse
// grid's mean radiance, per channel, below which neighbours' spreads are held to it. Kept
// out of prefiltered.comp, whose invocations share nothing: a workgroup barrier there made
// lavapipe run every phase of that shader three times as slowly.
//
// Phase 0: per workgroup, the sum of its coarse pixels. Phase 1 (one workgroup): the sum
// of those sums, the floor from it, and the counts reset for the refinement.

layout(local_size_x = 256) in;

const uint PARTIAL_SUMS = 0u;
const uint FLOOR = 1u;
const uint GROUP_SIZE = 256u;
// core/src/adaptive.rs: DARK_SHARE; prefiltered.comp: COARSE_STEP.
const float DARK_SHARE = 0.25;
const uint COARSE_STEP = 4u;

layout(push_constant) uniform Push {
    uint phase;
    uint width;         // the shaded image's
    uint coarse_width;  // coarse pixels per row
    uint coarse_count;
    uint partial_count; // phase 0's workgroups
    uint unused0;
    uint unused1;
    uint unused2;
} q;

layout(std430, binding = 0) readonly buffer Volume { vec4 volume[]; };
layout(std430, binding = 1) buffer Partials { vec4 partials[]; };
#define ADAPTIVE_STATE_BINDING 2
#include "adaptive_state.glsl"


shared vec4 sums[GROUP_SIZE];

// Sums `value` over the workgroup into sums[0], in a fixed order.
void sum_over_group(vec4 value) {
    uint t = gl_LocalInvocationIndex;
    sums[t] = value;
    barrier();
    for (uint half_size = GROUP_SIZE / 2u; half_size > 0u; half_size /= 2u) {
        if (t < half_size) {
            sums[t] += sums[t + half_size];
        }
        barrier();
    }
}

void main() {
    if (q.phase == PARTIAL_SUMS) {
        uint i = gl_GlobalInvocationID.x;
        vec4 value = vec4(0.0);
        if (i < q.coarse_count) {
            uint x = (i % q.coarse_width) * COARSE_STEP;
            uint y = (i / q.coarse_width) * COARSE_STEP;
            value = volume[y * q.width + x];
        }
        sum_over_group(value);
        if (gl_LocalInvocationIndex == 0u) {
            partials[gl_WorkGroupID.x] = sums[0];
        }
    } else {
        vec4 sum = vec4(0.0);
        for (uint i = gl_LocalInvocationIndex; i < q.partial_count; i += GROUP_SIZE) {
            sum += partials[i];
        }
        sum_over_group(sum);
        if (gl_LocalInvocationIndex == 0u) {
            state.floor_rgba = DARK_SHARE * sums[0] / float(max(q.coarse_count, 1u));
            state.listed = 0u;
            state.shaded = q.coarse_count;
        }
    }
}
