#version 450
// The reference ray march on the GPU: one invocation per output pixel, averaging its depth
// samples, writing the volume, visibility and depth layers.
#extension GL_GOOGLE_include_directive : require

layout(local_size_x = 8, local_size_y = 8) in;

#include "march_common.glsl"

vec3 shade_sample(vec2 pixel, vec3 origin, vec3 direction, float t_start, float t_end) {
    return reference_sample(origin, direction, t_start, t_end);
}

void main() {
    shade_output_pixel();
}
