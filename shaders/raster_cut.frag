#version 450
// The shadow map's fragment shader for frames with alpha-cut triangles: `raster.frag`,
// with samples where the triangle's mask is empty discarded.
#extension GL_GOOGLE_include_directive : require

#include "raster_cut.glsl"

layout(location = 0) flat in uint object_id;
layout(location = 1) in vec2 uv;
layout(location = 2) flat in uint mask;
layout(location = 0) out uint id;

void main() {
    if (cut_away(mask, uv)) {
        discard;
    }
    id = object_id;
}
