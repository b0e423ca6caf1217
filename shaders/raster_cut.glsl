// Alpha masks for the cut depth passes' fragment shaders: filtered and wrapped as
// `AlphaMask::alpha_at` (core/src/cutout.rs) does in f64.

struct Mask {
    uint offset;
    uint width;
    uint height;
    float threshold;
    // Bits 0-1 the wrap along u, 2-3 along v (`WRAP_*`), bit 4 set for closest filtering.
    uint sampling;
    // The alpha past a clipped edge.
    float border;
};

layout(std430, set = 0, binding = 5) readonly buffer Masks { Mask masks[]; };
layout(std430, set = 0, binding = 6) readonly buffer Texels { float texels[]; };

const uint OPAQUE = 0xffffffffu;
const uint WRAP_REPEAT = 0u;
const uint WRAP_EXTEND = 1u;
const uint WRAP_MIRROR = 2u;
const uint WRAP_CLIP = 3u;
const uint CLOSEST = 16u;

// `x` (in texels) moved by whole periods, or clamped, to where every index it reads is what
// it reads at `x`, so that indices stay small.
float near_edges(uint wrap, float x, float size) {
    if (wrap == WRAP_REPEAT) {
        return mod(x, size);
    }
    if (wrap == WRAP_MIRROR) {
        return mod(x, 2.0 * size);
    }
    return clamp(x, -2.0, size + 1.0);
}

// The texel read for index `i` (at least −2) of a side of `size` texels; −1 for none.
int wrapped(uint wrap, int i, int size) {
    if (wrap == WRAP_REPEAT) {
        return (i + 2 * size) % size;
    }
    if (wrap == WRAP_EXTEND) {
        return clamp(i, 0, size - 1);
    }
    if (wrap == WRAP_MIRROR) {
        int folded = (i + 2 * size) % (2 * size);
        return folded < size ? folded : 2 * size - 1 - folded;
    }
    return i >= 0 && i < size ? i : -1;
}

float texel(Mask m, int i, int j) {
    if (i < 0 || j < 0) {
        return m.border;
    }
    return texels[m.offset + uint(j) * m.width + uint(i)];
}

float alpha_at(Mask m, vec2 uv) {
    uint wrap_u = m.sampling & 3u;
    uint wrap_v = (m.sampling >> 2) & 3u;
    int width = int(m.width);
    int height = int(m.height);
    if ((m.sampling & CLOSEST) != 0u) {
        int i = int(floor(near_edges(wrap_u, uv.x * float(m.width), float(m.width))));
        int j = int(floor(near_edges(wrap_v, uv.y * float(m.height), float(m.height))));
        return texel(m, wrapped(wrap_u, i, width), wrapped(wrap_v, j, height));
    }
    float x = near_edges(wrap_u, uv.x * float(m.width) - 0.5, float(m.width));
    float y = near_edges(wrap_v, uv.y * float(m.height) - 0.5, float(m.height));
    float x0 = floor(x);
    float y0 = floor(y);
    float fx = x - x0;
    float fy = y - y0;
    int i0 = wrapped(wrap_u, int(x0), width);
    int i1 = wrapped(wrap_u, int(x0) + 1, width);
    int j0 = wrapped(wrap_v, int(y0), height);
    int j1 = wrapped(wrap_v, int(y0) + 1, height);
    float bottom = texel(m, i0, j0) + (texel(m, i1, j0) - texel(m, i0, j0)) * fx;
    float top = texel(m, i0, j1) + (texel(m, i1, j1) - texel(m, i0, j1)) * fx;
    return bottom + (top - bottom) * fy;
}

// Whether the sample lies where its triangle's mask is empty.
bool cut_away(uint mask_index, vec2 uv) {
    if (mask_index == OPAQUE) {
        return false;
    }
    return alpha_at(masks[mask_index], uv) < masks[mask_index].threshold;
}
