#version 450
// The camera depth's fragment shader for frames with alpha-cut triangles: depth alone,
// with samples where the triangle's mask is empty discarded.
#extension GL_GOOGLE_include_directive : require

#include "raster_cut.glsl"

layout(location = 1) in vec2 uv;
layout(location = 2) flat in uint mask;

void main() {
    if (cut_away(mask, uv)) {
        discard;
    }
}
