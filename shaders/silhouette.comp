#version 450
// Silhouette enhancement (core/src/silhouette.rs, Eq. 3): each texel walks the rays of its
// cone that cross it, sample by sample, as `apply_naive` does, and keeps the lowest
// result. The line set-up (per-column ray placement, depth transforms, kernel lengths per
// ray) comes from the CPU's own tables, and every expression is evaluated in the CPU's
// precision and order, without contraction, so the result equals the CPU's bit for bit.
// Ray placement runs in double precision, as on the CPU.

layout(local_size_x = 16, local_size_y = 16) in;

layout(push_constant) uniform Push {
    uint size;
    uint family_count;
    uint close;  // 1: dilation then erosion along the rays
    uint pad;
} pc;

// One family of rays (a pinhole cone or all orthographic lines); see `FamilyTables`.
struct Family {
    dvec2 epipole;  // epipole along the major and minor axes (pinhole)
    int x_major;
    int sign;
    int fan;
    int first_ray;
    int last_ray;
    int steps_first;  // ray of steps[steps_offset]
    int steps_count;
    int steps_offset;
    float base;
};

// Per family and column: ray placement (along, shift, inv_along, inv_shift).
struct Placement {
    dvec4 coefficients;
};

// Per family and column: the depth transform, and the row offset of line 0
// (orthographic) or whether the rays visit the column (pinhole).
struct Column {
    float scale;
    float offset;
    float unscale;
    int info;
};

layout(std430, binding = 0) readonly buffer Source { float src[]; };
layout(std430, binding = 1) writeonly buffer Target { float dst[]; };
layout(std430, binding = 2) readonly buffer Families { Family families[]; };
layout(std430, binding = 3) readonly buffer Placements { Placement placements[]; };
layout(std430, binding = 4) readonly buffer Columns { Column columns[]; };
layout(std430, binding = 5) readonly buffer Steps { uint steps[]; };

const uint INFINITY_BITS = 0x7f800000u;
const uint LOWEST_BITS = 0xff7fffffu;  // f32::MIN

// The CPU's `min`/`max` picks, operand order included.
float pick_min(float a, float b) { return b < a ? b : a; }
float pick_max(float a, float b) { return b > a ? b : a; }

// The CPU's floor of a texel coordinate: the truncation of x shifted by 2^20. Far outside
// the map the value is clamped, which keeps it outside.
int texel_floor(double x) {
    precise double shifted = max(x, -1.0e12lf) + 1048576.0lf;
    double whole = clamp(trunc(shifted), -1073741824.0lf, 1073741824.0lf);
    return int(whole) - 1048576;
}

int column_at(uint f, int q) { return int(f * pc.size) + q; }

// The minor index ray `ray` samples at column q.
int ray_row(uint f, int ray, int q) {
    if (families[f].fan == 0) {
        return ray + columns[column_at(f, q)].info;
    }
    dvec4 c = placements[column_at(f, q)].coefficients;
    precise double placed = (double(ray) + 0.5lf) * c.x + c.y;
    return texel_floor(placed);
}

// The ray passing nearest the centre of texel (q, r).
int nearest_ray(uint f, int q, int r) {
    if (families[f].fan == 0) {
        return r - columns[column_at(f, q)].info;
    }
    dvec4 c = placements[column_at(f, q)].coefficients;
    precise double placed = (double(r) + 0.5lf) * c.z - c.w;
    return texel_floor(placed);
}

bool in_cone(uint f, int q, int r) {
    if (families[f].fan == 0) {
        return true;
    }
    precise double along = (double(q) + 0.5lf) - families[f].epipole.x;
    precise double across = (double(r) + 0.5lf) - families[f].epipole.y;
    bool nearer = families[f].x_major != 0 ? abs(along) >= abs(across) : abs(along) > abs(across);
    return nearer && along * double(families[f].sign) > 0.0lf;
}

// The kernel length in columns of ray `ray`.
uint ray_steps(uint f, int ray) {
    int index = clamp(ray - families[f].steps_first, 0, families[f].steps_count - 1);
    return steps[families[f].steps_offset + index];
}

// The column j steps from q along the rays, or −1 where the rays do not go.
int step_column(uint f, int q, int j) {
    int s = q + families[f].sign * j;
    if (s < 0 || s >= int(pc.size)) {
        return -1;
    }
    if (families[f].fan != 0 && columns[column_at(f, s)].info == 0) {
        return -1;
    }
    return s;
}

// Whether ray `ray` samples the map at column q, and the depth there.
bool sample_depth(uint f, int ray, int q, out float z) {
    int r = ray_row(f, ray, q);
    int n = int(pc.size);
    if (r < 0 || r >= n) {
        z = 0.0;
        return false;
    }
    z = src[families[f].x_major != 0 ? r * n + q : q * n + r];
    return true;
}

float forward(uint f, int q, float z) {
    Column c = columns[column_at(f, q)];
    precise float u = (z - families[f].base) * c.scale - c.offset;
    return u;
}

float back(uint f, int q, float u) {
    Column c = columns[column_at(f, q)];
    precise float z = families[f].base + (u + c.offset) * c.unscale;
    return pick_max(z, uintBitsToFloat(LOWEST_BITS));
}

float dilation(uint f, int ray, int q, float own) {
    float lowest = uintBitsToFloat(INFINITY_BITS);
    int n = int(ray_steps(f, ray));
    for (int j = 1; j <= n; ++j) {
        int s = step_column(f, q, -j);
        if (s < 0) {
            break;
        }
        float z;
        if (sample_depth(f, ray, s, z)) {
            lowest = pick_min(lowest, forward(f, s, z));
        }
    }
    return pick_min(own, back(f, q, lowest));
}

float along_ray(uint f, int ray, int q, float own) {
    float dilated = dilation(f, ray, q, own);
    if (pc.close == 0u) {
        return dilated;
    }
    float highest = -uintBitsToFloat(INFINITY_BITS);
    int n = int(ray_steps(f, ray));
    for (int j = 1; j <= n; ++j) {
        int s = step_column(f, q, j);
        if (s < 0) {
            break;
        }
        float z;
        if (sample_depth(f, ray, s, z)) {
            highest = pick_max(highest, forward(f, s, dilation(f, ray, s, z)));
        }
    }
    return pick_min(own, pick_max(dilated, back(f, q, highest)));
}

void main() {
    ivec2 id = ivec2(gl_GlobalInvocationID.xy);
    int n = int(pc.size);
    if (id.x >= n || id.y >= n) {
        return;
    }
    int index = id.y * n + id.x;
    float own = src[index];
    uint f = 0u;
    int q = 0;
    int r = 0;
    bool found = false;
    for (; f < pc.family_count; ++f) {
        q = families[f].x_major != 0 ? id.x : id.y;
        r = families[f].x_major != 0 ? id.y : id.x;
        if (in_cone(f, q, r)) {
            found = true;
            break;
        }
    }
    if (!found) {
        dst[index] = own;
        return;
    }
    // The rays that cross the texel: a contiguous range around the nearest one.
    int first = families[f].first_ray;
    int last = families[f].last_ray;
    int nearest = nearest_ray(f, q, r);
    int ray = clamp(nearest, first, last);
    while (ray > first && ray_row(f, ray, q) > r) {
        --ray;
    }
    while (ray < last && ray_row(f, ray, q) < r) {
        ++ray;
    }
    if (ray_row(f, ray, q) != r) {
        dst[index] = along_ray(f, nearest, q, own);
        return;
    }
    int lo = ray;
    int hi = ray;
    while (lo > first && ray_row(f, lo - 1, q) == r) {
        --lo;
    }
    while (hi < last && ray_row(f, hi + 1, q) == r) {
        ++hi;
    }
    float lowest = uintBitsToFloat(INFINITY_BITS);
    for (int k = lo; k <= hi; ++k) {
        lowest = pick_min(lowest, along_ray(f, k, q, own));
    }
    dst[index] = lowest;
}
