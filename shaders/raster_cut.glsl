// Alpha masks for the cut depth passes' fragment shaders: filtered bilinearly between texel
// centres and repeating, as `AlphaMask::alpha_at` (core/src/cutout.rs) does in f64.

struct Mask {
    uint offset;
    uint width;
    uint height;
    float threshold;
};

layout(std430, set = 0, binding = 5) readonly buffer Masks { Mask masks[]; };
layout(std430, set = 0, binding = 6) readonly buffer Texels { float texels[]; };

const uint OPAQUE = 0xffffffffu;

float texel(Mask m, uint i, uint j) {
    return texels[m.offset + j * m.width + i];
}

// Whether the sample lies where its triangle's mask is empty.
bool cut_away(uint mask_index, vec2 uv) {
    if (mask_index == OPAQUE) {
        return false;
    }
    Mask m = masks[mask_index];
    float x = mod(uv.x * float(m.width) - 0.5, float(m.width));
    float y = mod(uv.y * float(m.height) - 0.5, float(m.height));
    float x0 = floor(x);
    float y0 = floor(y);
    float fx = x - x0;
    float fy = y - y0;
    // mod may round up to the width itself: wrap the index too.
    uint i0 = uint(x0) % m.width;
    uint j0 = uint(y0) % m.height;
    uint i1 = (i0 + 1u) % m.width;
    uint j1 = (j0 + 1u) % m.height;
    float bottom = texel(m, i0, j0) + (texel(m, i1, j0) - texel(m, i0, j0)) * fx;
    float top = texel(m, i0, j1) + (texel(m, i1, j1) - texel(m, i0, j1)) * fx;
    return bottom + (top - bottom) * fy < m.threshold;
}
