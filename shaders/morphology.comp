#version 450
// Flat grey-scale morphology of the shadow map's depth (core/src/morphology.rs): the
// extremum over a kernel given as one horizontal chord per row offset. A disk runs as one
// pass; a box as a row pass and a column pass (`vertical` swaps the axes). Texels outside
// the map take no part.

layout(local_size_x = 16, local_size_y = 16) in;

layout(push_constant) uniform Push {
    uint size;
    int rows;       // row offsets run over [−rows, rows]
    uint vertical;
    uint take_max;  // 1: maximum (erosion), 0: minimum (dilation)
} pc;

layout(std430, binding = 0) readonly buffer Source { float src[]; };
layout(std430, binding = 1) writeonly buffer Target { float dst[]; };
// Chord half-width per row offset, −1 where the row holds no kernel texel.
layout(std430, binding = 2) readonly buffer Chords { int half_widths[]; };

void main() {
    ivec2 id = ivec2(gl_GlobalInvocationID.xy);
    int n = int(pc.size);
    if (id.x >= n || id.y >= n) {
        return;
    }
    float best = src[id.y * n + id.x];
    bool take_max = pc.take_max != 0u;
    for (int dy = -pc.rows; dy <= pc.rows; ++dy) {
        int w = half_widths[dy + pc.rows];
        for (int dx = -w; dx <= w; ++dx) {
            ivec2 at = pc.vertical != 0u ? ivec2(id.x + dy, id.y + dx) : ivec2(id.x + dx, id.y + dy);
            if (at.x < 0 || at.y < 0 || at.x >= n || at.y >= n) {
                continue;
            }
            float v = src[at.y * n + at.x];
            best = take_max ? max(best, v) : min(best, v);
        }
    }
    dst[id.y * n + id.x] = best;
}
