#version 450
// Epipolar rectification (core/src/epipolar.rs, EpipolarMap::resample): every sample of
// every slice reads the shadow-map texel under its centre and stores K, the threshold a
// view ray's depth slope is compared with.

layout(local_size_x = 64, local_size_y = 1) in;

layout(push_constant) uniform Push {
    vec4 epipole_along;  // radial: epipole xy; parallel: direction xy
    vec4 normal;         // parallel: normal xy
    float first;         // slice angle or offset origin, and its step
    float step;
    float spacing_first; // s of sample i's centre: spacing_first + (i + ½)·spacing_step
    float spacing_step;
    float camera_depth;  // radial: the camera's light depth
    float slope;         // parallel: depth slope along a slice
    float bias;
    uint radial;
    uint slices;
    uint samples;
    uint map_size;
    uint unused;
} pc;

layout(std430, binding = 0) readonly buffer ShadowDepth { float shadow_depth[]; };
layout(std430, binding = 1) writeonly buffer Values { float values[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint slice = gl_GlobalInvocationID.y;
    if (i >= pc.samples || slice >= pc.slices) {
        return;
    }
    float s = pc.spacing_first + (float(i) + 0.5) * pc.spacing_step;
    vec2 base;
    vec2 direction;
    if (pc.radial != 0u) {
        float angle = pc.first + float(slice) * pc.step;
        base = pc.epipole_along.xy;
        direction = vec2(cos(angle), sin(angle));
    } else {
        base = pc.normal.xy * (pc.first + float(slice) * pc.step);
        direction = pc.epipole_along.xy;
    }
    vec2 p = base + direction * s;
    float size = float(pc.map_size);
    // Outside the map nothing occludes.
    float occluder = 1.0 / 0.0;
    if (p.x >= 0.0 && p.y >= 0.0 && p.x < size && p.y < size) {
        occluder = shadow_depth[uint(p.y) * pc.map_size + uint(p.x)];
    }
    float lit_below = occluder + pc.bias;
    values[slice * pc.samples + i] =
        pc.radial != 0u ? (lit_below - pc.camera_depth) / s : lit_below - pc.slope * s;
}
