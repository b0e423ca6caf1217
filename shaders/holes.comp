#version 450
// Hole creation (core/src/holes.rs, Eq. 4–5): where a texel's occluder is one of the chosen
// objects and the animated Perlin fBm there lies below the threshold, the occluder is
// removed (depth +∞); every other texel keeps its depth bit for bit. Each texel evaluates
// `HoleNoise` itself: its block's lattice placement in double precision (reduced to one
// period as on the CPU), then the two-step lookup in single precision with the same
// hashing, gradients and fade, in the CPU's order and without contraction, so the noise
// and the holes equal the CPU's bit for bit.

layout(local_size_x = 16, local_size_y = 16) in;

struct Octave {
    dvec2 shift;   // in this octave's cells
    double scale;  // 2^i
    float weight;
    uint seed;
};

layout(std430, binding = 0) readonly buffer Source { float src[]; };
layout(std430, binding = 1) readonly buffer Ids { uint ids[]; };
layout(std430, binding = 2) readonly buffer Params {
    dvec2 origin;    // q at the centre of texel (0, 0), in first-octave cells
    dvec2 per_x;     // its change per texel in x
    dvec2 per_y;     // and in y
    dvec2 rotation;  // (cos θ, sin θ) of the first lookup
    uint size;
    uint octave_count;
    uint block;         // texels per evaluation block along a row
    uint object_count;
    uint period_whole;  // the lattice period in cells
    uint period_mask;   // period − 1 where it is a power of two above 1, else 0
    float period_cells;
    float period_inverse;
    float threshold;
    float warp;
    float perlin_scale;
    Octave octaves[16];
} p;
// The chosen object ids, sorted.
layout(std430, binding = 3) readonly buffer Objects { uint objects[]; };
layout(std430, binding = 4) writeonly buffer Target { float dst[]; };

const uint INFINITY_BITS = 0x7f800000u;

// Where one octave's samples of a block lie: lane k at base + k·step (+ the warp).
struct Laid {
    float base_x;
    float base_y;
    float step_x;
    float step_y;
    float scale;
};

// f64 rem_euclid by the period: the exact remainder with the dividend's sign (the
// quotient's rounding corrected), then the CPU's one rounded addition for a negative one.
double rem_euclid(double a, double period) {
    double k = trunc(a / period);
    precise double r = a - k * period;
    if (a >= 0.0lf ? r < 0.0lf : r > 0.0lf) {
        k += a >= 0.0lf ? -1.0lf : 1.0lf;
        r = a - k * period;
    } else if (a >= 0.0lf ? r >= period : r <= -period) {
        k += a >= 0.0lf ? 1.0lf : -1.0lf;
        r = a - k * period;
    }
    precise double euclid = r < 0.0lf ? r + period : r;
    return euclid;
}

Laid lay(uint octave, dvec2 at, dvec2 step) {
    double scale = p.octaves[octave].scale;
    precise dvec2 base = at * scale + p.octaves[octave].shift;
    precise dvec2 scaled = step * scale;
    double period = double(p.period_whole);
    return Laid(float(rem_euclid(base.x, period)), float(rem_euclid(base.y, period)),
                float(scaled.x), float(scaled.y), float(scale));
}

dvec2 rotate(dvec2 v) {
    precise double x = p.rotation.x * v.x - p.rotation.y * v.y;
    precise double y = p.rotation.y * v.x + p.rotation.x * v.y;
    return dvec2(x, y);
}

uint lattice_hash(uint point) {
    uint h = point * 0x7feb352du;
    return (h ^ (h >> 15)) * 0x846ca68bu;
}

float gradient(uint hash, float dx, float dy) {
    bool swap = (hash & 0x20000000u) != 0u;
    float major = swap ? dy : dx;
    float minor = swap ? dx : dy;
    major = uintBitsToFloat(floatBitsToUint(major) ^ (hash & 0x80000000u));
    minor = (hash & 0x40000000u) != 0u ? -minor : minor;
    precise float g = major + 0.5 * minor;
    return g;
}

// The lattice cell of x along one axis: the fraction within it and its two wrapped ends.
void cell(float x, out float fraction, out uint low, out uint high) {
    float whole = floor(x);
    precise float f = x - whole;
    fraction = f;
    if (p.period_mask != 0u) {
        uint bits = uint(int(whole));
        low = bits & p.period_mask;
        high = (bits + 1u) & p.period_mask;
        return;
    }
    precise float wrapped = whole - p.period_cells * floor(whole * p.period_inverse);
    if (wrapped >= p.period_cells) {
        wrapped -= p.period_cells;
    }
    if (wrapped < 0.0) {
        wrapped += p.period_cells;
    }
    precise float next = wrapped + 1.0;
    low = uint(wrapped);
    high = next >= p.period_cells ? 0u : uint(next);
}

float fade(float t) {
    precise float f = t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    return f;
}

float perlin(float x, float y, uint seed) {
    float dx, dy;
    uint x0, x1, y0, y1;
    cell(x, dx, x0, x1);
    cell(y, dy, y0, y1);
    uint row0 = y0 * p.period_whole;
    uint row1 = y1 * p.period_whole;
    precise float dx1 = dx - 1.0;
    precise float dy1 = dy - 1.0;
    float n00 = gradient(lattice_hash((row0 + x0) ^ seed), dx, dy);
    float n10 = gradient(lattice_hash((row0 + x1) ^ seed), dx1, dy);
    float n01 = gradient(lattice_hash((row1 + x0) ^ seed), dx, dy1);
    float n11 = gradient(lattice_hash((row1 + x1) ^ seed), dx1, dy1);
    float u = fade(dx);
    float v = fade(dy);
    precise float bottom = n00 + u * (n10 - n00);
    precise float top = n01 + u * (n11 - n01);
    precise float value = p.perlin_scale * (bottom + v * (top - bottom));
    return value;
}

bool chosen(uint id) {
    uint lo = 0u;
    uint hi = p.object_count;
    while (lo < hi) {
        uint mid = (lo + hi) / 2u;
        if (objects[mid] < id) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return lo < p.object_count && objects[lo] == id;
}

// N at texel (x, y): the two-step lookup of `HoleNoise`, in [0, 1].
float noise(uint x, uint y) {
    uint x0 = x - x % p.block;
    precise dvec2 at = p.origin + p.per_x * double(x0) + p.per_y * double(y);
    precise float lane = float(x - x0);
    float offset = 0.0;
    if (p.warp != 0.0) {
        precise float half_warp = 0.5 * p.warp;
        Laid first = lay(0u, rotate(at), rotate(p.per_x));
        precise float fx = first.base_x + lane * first.step_x;
        precise float fy = first.base_y + lane * first.step_y;
        precise float moved = half_warp * perlin(fx, fy, p.octaves[0].seed);
        offset = moved;
    }
    precise float sum = 0.0;
    for (uint i = 0u; i < p.octave_count; ++i) {
        Laid octave = lay(i, at, p.per_x);
        precise float shift = octave.scale * offset;
        precise float ox = octave.base_x + lane * octave.step_x + shift;
        precise float oy = octave.base_y + lane * octave.step_y + shift;
        sum += p.octaves[i].weight * perlin(ox, oy, p.octaves[i].seed);
    }
    precise float n = 0.5 + 0.5 * sum;
    return clamp(n, 0.0, 1.0);
}

void main() {
    uvec2 id = gl_GlobalInvocationID.xy;
    if (id.x >= p.size || id.y >= p.size) {
        return;
    }
    uint index = id.y * p.size + id.x;
    float depth = src[index];
    if (chosen(ids[index]) && noise(id.x, id.y) < p.threshold) {
        depth = uintBitsToFloat(INFINITY_BITS);
    }
    dst[index] = depth;
}
