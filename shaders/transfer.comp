#version 450
// Transfer-function application (core/src/transfer_function.rs): a bilinear lookup in the
// baked TF at (V̄, normalized depth), then the colour or monochrome rule, in place on the
// premultiplied volume layer.
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = 256) in;

layout(push_constant) uniform Push {
    uint pixels;
    uint size;       // TF texels per side
    float near;
    float inv_range;
    uint monochrome;
    uint unused0;
    uint unused1;
    uint unused2;
    vec4 per_light[3]; // rows of M in K = M·L (colour mode)
} pc;

layout(std430, binding = 0) readonly buffer Texels { vec4 texels[]; };
layout(std430, binding = 1) readonly buffer Visibility { float visibility[]; };
layout(std430, binding = 2) readonly buffer Depth { float depth[]; };
layout(std430, binding = 3) buffer Volume { vec4 volume[]; };

// Texel (i, j) of the TF padded by one repeated edge texel on each side.
vec4 padded(int i, int j) {
    int n = int(pc.size);
    return texels[clamp(j - 1, 0, n - 1) * n + clamp(i - 1, 0, n - 1)];
}

void main() {
    uint index = gl_GlobalInvocationID.x;
    if (index >= pc.pixels) {
        return;
    }
    float scale = float(pc.size);
    float x = unit(visibility[index]) * scale + 0.5;
    float y = unit((depth[index] - pc.near) * pc.inv_range) * scale + 0.5;
    int i = int(floor(x));
    int j = int(floor(y));
    float fx = x - float(i);
    float fy = y - float(j);
    vec4 upper = mix(padded(i, j), padded(i + 1, j), fx);
    vec4 lower = mix(padded(i, j + 1), padded(i + 1, j + 1), fx);
    vec4 t = upper + fy * (lower - upper);
    vec4 px = volume[index];
    vec3 l = vec3(finite_or_zero(px.r), finite_or_zero(px.g), finite_or_zero(px.b));
    float keep = 1.0 - t.a;
    vec3 result;
    if (pc.monochrome != 0u) {
        float luminance = 0.2126 * t.r + 0.7152 * t.g + 0.0722 * t.b;
        result = (keep + luminance) * l;
    } else {
        vec3 k = vec3(dot(pc.per_light[0].xyz, l), dot(pc.per_light[1].xyz, l), dot(pc.per_light[2].xyz, l));
        result = keep * l + t.rgb * k;
    }
    volume[index] = vec4(finite_or_zero(result.r), finite_or_zero(result.g), finite_or_zero(result.b), unit(px.a));
}
