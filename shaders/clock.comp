#version 450
#extension GL_ARB_shader_clock : require
// The shader cores' clock (core/src/gpu/clock.rs): one invocation reads its subgroup's
// cycle counter around a dependent chain of fused multiply-adds; the host divides the
// cycles by the dispatch's timestamped duration. Needs VK_KHR_shader_clock.

layout(local_size_x = 1) in;

layout(push_constant) uniform Push {
    uint iterations;
    float seed;
    uint unused[2];  // the host packs push constants in whole 16-byte rows
} pc;

// (start, end) cycle counts as 2×32 bits each, and the chain's result, which keeps it.
layout(std430, binding = 0) writeonly buffer Readings {
    uvec4 cycles;
    float sink;
};

void main() {
    uvec2 start = clock2x32ARB();
    float x = pc.seed;
    for (uint i = 0u; i < pc.iterations; ++i) {
        x = fma(x, 0.999, 0.5);
    }
    uvec2 end = clock2x32ARB();
    cycles = uvec4(start, end);
    sink = x;
}
