#version 450
// Prefiltered per-pixel evaluation (core/src/prefiltered.rs, Prefiltered::march): locate
// the ray in the rectified map, blend the filtered basis' prefix rows of the bands and
// slices around it, and dot them with the ray's coefficients. Pixels near an on-screen
// epipole, rays along the light, rays too short for the prefix sums and rays too far along
// a slice for their precision take the fallback march, as on the CPU.
#extension GL_GOOGLE_include_directive : require

layout(local_size_x = 8, local_size_y = 8) in;

#include "march_common.glsl"

const uint RADIAL = 0u;
const uint PARALLEL = 1u;
const uint PROJECTIVE = 2u;
const uint KNOTS = 9u;
const float TABLE_STEPS = 8192.0;
const float WARP_MARGIN = 0.1;
// core/src/prefiltered.rs: BOX_PIECE_DEPTH, BOX_PIECE_VIEW_DEPTH, MAX_BOX_PIECES, ALONG_THE_LIGHT_SIN; core/src/epipolar.rs:
// SHORT_RAY_TEXELS, SHORT_STRETCH_TEXELS, LOOKUP_DEPTH.
const float BOX_PIECE_DEPTH = 0.05;
const float BOX_PIECE_VIEW_DEPTH = 0.5;
const uint MAX_BOX_PIECES = 20u;
const float SHORT_RAY_TEXELS = 64.0;
const float SHORT_STRETCH_TEXELS = 16.0;
const float LOOKUP_DEPTH = 1.0;
const float ALONG_THE_LIGHT_SIN = 0.15;
// core/src/prefiltered.rs: EXACT_END_WIDTH, MAX_EXACT_END_SAMPLES, SAMPLES_PER_ROW.
const float EXACT_END_WIDTH = 0.35;
// core/src/prefiltered.rs: BLUR_WIDTH (EXACT_END_WIDTH / 16) in coefficient-table rows, and
// BLURRED_SHARE_LIMIT.
const uint BLUR_ROWS = 179u;
const float BLURRED_SHARE_LIMIT = 0.1;
const uint MAX_EXACT_END_SAMPLES = 64u;
const float SAMPLES_PER_ROW = 2.0;

layout(std430, binding = 6) readonly buffer PrefilteredParams {
    mat4 from_world;    // texel_from_world, or view_from_world for projective maps
    vec4 epipoles;      // up to two on-screen epipoles, (x0, y0, x1, y1)
    vec4 along_normal;  // parallel slices: direction xy, normal xy
    float first;        // slice coordinate origin and step
    float step;
    float slope;
    float spacing_first;
    float spacing_step;
    float block;
    uint map_layout;
    uint full_circle;
    uint reciprocal_spacing;
    uint slices;
    uint samples;
    uint stride;
    uint snorm;
    uint epipole_count;
    uint near_plane_correction;
    uint exact_ray_ends;
    uint frequencies;   // M/2
    float bands_per_octave;
    float dark_lookup_limit;  // looked-up visibility below which a ray is marched
    float key_scale;    // what turns a pinhole camera's K into a slope free of units
} q;

// Per band: its warp's KNOTS knots.
layout(std430, binding = 7) readonly buffer BandKnots { float band_knots[]; };
layout(std430, binding = 8) readonly buffer SliceBands { uvec2 slice_bands[]; };
layout(std430, binding = 9) readonly buffer Bands { uvec2 bands[]; };
layout(std430, binding = 10) readonly buffer Weight { float weight[]; };
// Rows are whole lanes of 8 values: 16 bytes of snorm16 or 32 of f32, read as uvec4.
layout(std430, binding = 11) readonly buffer Basis { uvec4 basis4[]; };
layout(std430, binding = 12) readonly buffer Coefficients { vec4 coefficients4[]; };
// Per slice: log₂ of its fastest ray's speed.
layout(std430, binding = 13) readonly buffer SliceSpeeds { float log2_fastest[]; };
// The rectified map (EpipolarMap::values): `samples` values per slice.
layout(std430, binding = 14) readonly buffer Rectified { float rectified[]; };
// Per sample index: what turns K at its centre into K at its ends (sample_bounds).
layout(std430, binding = 15) readonly buffer BoundFactors { vec2 bound_factors[]; };
// The uniformity table (uniformity.comp, core/src/uniformity.rs).
layout(std430, binding = 16) readonly buffer Runs { vec2 runs[]; };
// core/src/uniformity.rs: BLOCK.
const uint UNIFORMITY_BLOCK = 16u;

const float TAU = 6.28318530717959;

float wrap_from(float angle, float low) {
    if (isinf(angle) || isnan(angle)) {
        return low;
    }
    for (int i = 0; i < 8 && angle < low; ++i) {
        angle += TAU;
    }
    for (int i = 0; i < 8 && angle >= low + TAU; ++i) {
        angle -= TAU;
    }
    return angle;
}

// (slice coordinate, s at t = 0, s per unit t, threshold); false along the light.
bool locate(vec3 origin, vec3 direction, out vec4 located) {
    if (q.map_layout == PROJECTIVE) {
        vec3 d = mat3(q.from_world) * direction;
        if (!(d.x >= 1e-9)) {
            return false;
        }
        located = vec4((d.y / d.x - q.first) / q.step, (q.from_world * vec4(origin, 1.0)).x, d.x, d.z / d.x);
        return true;
    }
    vec3 o = (q.from_world * vec4(origin, 1.0)).xyz;
    vec3 d = mat3(q.from_world) * direction;
    float s_per_t = length(d.xy);
    if (!(s_per_t >= 1e-9)) {
        return false;
    }
    if (q.map_layout == RADIAL) {
        float turns = atan(d.y, d.x) - q.first;
        turns = q.full_circle != 0u ? wrap_from(turns, 0.0) : wrap_from(turns, -PI);
        located = vec4(turns / q.step, 0.0, s_per_t, d.z / s_per_t);
        return true;
    }
    float s_origin = dot(q.along_normal.xy, o.xy);
    float offset = dot(q.along_normal.zw, o.xy);
    located = vec4((offset - q.first) / q.step, s_origin, s_per_t, o.z - q.slope * s_origin);
    return true;
}

float order_key(float value) {
    if (q.map_layout == PARALLEL) {
        return -value;
    }
    if (isinf(value)) {
        return -sign(value);
    }
    float slope = value * q.key_scale;
    return -slope / (1.0 + abs(slope));
}

float sample_coordinate(float s) {
    if (q.reciprocal_spacing == 0u) {
        return (s - q.spacing_first) / q.spacing_step;
    }
    return s > 0.0 ? (q.spacing_first - 1.0 / s) / q.spacing_step : -BIG;
}

float warp(uint band, float key) {
    uint base = band * KNOTS;
    uint index = 0u;
    for (uint i = 1u; i < KNOTS - 1u; ++i) {
        if (band_knots[base + i] <= key) {
            index += 1u;
        }
    }
    float a = band_knots[base + index];
    float b = band_knots[base + index + 1u];
    float within = b > a ? (key - a) / (b - a) : 0.0;
    float local = (float(index) + within) / float(KNOTS - 1u);
    return clamp(WARP_MARGIN + (1.0 - 2.0 * WARP_MARGIN) * local, 0.0, 1.0);
}

// Lower boundary and fraction towards the next, clamped to a band of `rows` rows.
void boundary(float x, uint rows, out uint lower, out float fraction) {
    uint last = rows - 1u;
    float clamped = clamp(x, 0.0, float(last));
    lower = min(uint(clamped), last);
    fraction = lower == last ? 0.0 : clamped - float(lower);
}

// Σ_r factor_r · ⟨basis row r, coefficients⟩, four lanes at a time.
float blend_dot(uint rows[4], float factors[4], uint coefficient_row) {
    float dot_ = 0.0;
    uint quads = q.stride / 4u;
    uint coefficient_base = coefficient_row * quads;
    if (q.snorm != 0u) {
        uint octets = q.stride / 8u;
        for (uint c = 0u; c < octets; ++c) {
            vec4 low = vec4(0.0);
            vec4 high = vec4(0.0);
            for (uint r = 0u; r < 4u; ++r) {
                if (factors[r] != 0.0) {
                    uvec4 w = basis4[rows[r] * octets + c];
                    low += factors[r] * vec4(unpackSnorm2x16(w.x), unpackSnorm2x16(w.y));
                    high += factors[r] * vec4(unpackSnorm2x16(w.z), unpackSnorm2x16(w.w));
                }
            }
            dot_ += dot(low, coefficients4[coefficient_base + 2u * c]);
            dot_ += dot(high, coefficients4[coefficient_base + 2u * c + 1u]);
        }
    } else {
        for (uint c = 0u; c < quads; ++c) {
            vec4 blended = vec4(0.0);
            for (uint r = 0u; r < 4u; ++r) {
                if (factors[r] != 0.0) {
                    blended += factors[r] * uintBitsToFloat(basis4[rows[r] * quads + c]);
                }
            }
            dot_ += dot(blended, coefficients4[coefficient_base + c]);
        }
    }
    return dot_;
}

// The two slices to blend at slice coordinate `x`, and the share of the upper one
// (EpipolarMap::neighbours).
void neighbours(float x, out uint lower, out uint upper, out float fraction) {
    uint last = q.slices - 1u;
    float clamped;
    if (q.full_circle != 0u) {
        float count = float(q.slices);
        float c = x < 0.0 ? x + count : (x >= count ? x - count : x);
        clamped = clamp(c, 0.0, count);
    } else {
        clamped = clamp(x, 0.0, float(last));
    }
    lower = min(uint(clamped), last);
    fraction = clamped - float(lower);
    upper = lower == last ? (q.full_circle != 0u ? 0u : last) : lower + 1u;
}

// The two bands of `slice` (indices within it) that bracket a ray crossing 2^log2_rate
// texels per unit t, and the share of the second (Prefiltered::bands_for).
void bands_at(uint slice, float log2_rate, out uint j, out uint next, out float fraction) {
    uint count = slice_bands[slice].y;
    float position = clamp((log2_fastest[slice] - log2_rate) * q.bands_per_octave, 0.0,
                           float(count - 1u));
    j = min(uint(position), count - 1u);
    fraction = position - float(j);
    next = min(j + 1u, count - 1u);
}

// The smallest and largest K over sample i's interval (EpipolarMap::sample_bounds).
vec2 sample_bounds(uint i, float centre) {
    return sample_bounds_from(bound_factors[i], centre, q.map_layout != PARALLEL);
}

// Whether bounds (lowest, highest K) are all lit, or all shadowed, for `threshold`.
bool is_uniform(vec2 bounds, float threshold, bool lit) {
    return lit ? bounds.x >= threshold : bounds.y < threshold;
}

// Whether samples [from, to) of the slice starting at `row` are all as `lit` says.
bool run_is_uniform(uint row, uint from, uint to, float threshold, bool lit) {
    for (uint i = from; i < to; ++i) {
        if (!is_uniform(sample_bounds(i, rectified[row + i]), threshold, lit)) {
            return false;
        }
    }
    return true;
}

// Whether samples [from, to) of the slice starting at `row`, all in block `block` of the
// slice's table at `table`, are all as `lit` says: where the whole block is (one entry),
// or else read sample by sample.
bool partial_is_uniform(uint table, uint block, uint row, uint from, uint to,
                        float threshold, bool lit) {
    return is_uniform(runs[table + block], threshold, lit)
        || run_is_uniform(row, from, to, threshold, lit);
}

// Whether a ray with `threshold` is lit (`lit` true) or shadowed over all of samples
// first..=last of `slice` (UniformityTable::uniformity).
bool uniformity(uint slice, float threshold, uint first, uint last, out bool lit) {
    uint row = slice * q.samples;
    vec2 b = sample_bounds(first, rectified[row + first]);
    if (b.x >= threshold) {
        lit = true;
    } else if (b.y < threshold) {
        lit = false;
    } else {
        return false;
    }
    if (last == first) {
        return true;
    }
    if (!is_uniform(sample_bounds(last, rectified[row + last]), threshold, lit)) {
        return false;
    }
    uint blocks = (q.samples + UNIFORMITY_BLOCK - 1u) / UNIFORMITY_BLOCK;
    uint levels = uint(findMSB(blocks)) + 1u;
    uint table = slice * levels * blocks;
    uint first_block = first / UNIFORMITY_BLOCK;
    uint last_block = last / UNIFORMITY_BLOCK;
    if (first_block == last_block) {
        return partial_is_uniform(table, first_block, row, first + 1u, last, threshold, lit);
    }
    if (!partial_is_uniform(table, first_block, row, first + 1u,
                            (first_block + 1u) * UNIFORMITY_BLOCK, threshold, lit)
        || !partial_is_uniform(table, last_block, row, last_block * UNIFORMITY_BLOCK, last,
                               threshold, lit)) {
        return false;
    }
    uint whole = last_block - first_block - 1u;
    if (whole > 0u) {
        uint k = uint(findMSB(whole));
        uint level = table + k * blocks;
        if (!is_uniform(runs[level + first_block + 1u], threshold, lit)
            || !is_uniform(runs[level + last_block - (1u << k)], threshold, lit)) {
            return false;
        }
    }
    return true;
}

// The exact visibility between boundary positions x0 < x1 where each slice the ray reads
// is lit, or shadowed, all along (Prefiltered::uniform_visibility); false otherwise.
bool uniform_visibility(vec4 located, float x0, float x1, out float visibility) {
    visibility = 0.0;
    float samples = float(q.samples);
    float c0 = max(x0, 0.0) * SAMPLES_PER_ROW;
    float c1 = x1 * SAMPLES_PER_ROW;
    if (!(c0 < c1 && c0 < samples)) {
        return false;
    }
    bool past_the_end = c1 > samples;
    uint first = uint(c0);
    uint last = min(uint(ceil(c1)), q.samples) - 1u;
    uint lower_slice, upper_slice;
    float slice_fraction;
    neighbours(located.x, lower_slice, upper_slice, slice_fraction);
    for (uint n = 0u; n < 2u; ++n) {
        uint slice = n == 0u ? lower_slice : upper_slice;
        float share = n == 0u ? 1.0 - slice_fraction : slice_fraction;
        if (share == 0.0) {
            continue;
        }
        bool lit;
        if (!uniformity(slice, located.w, first, last, lit) || (!lit && past_the_end)) {
            return false;
        }
        if (lit) {
            visibility += share;
        }
    }
    return true;
}

// What average() makes of a stretch of a ray (prefiltered.rs: Average).
const uint AVERAGE_VISIBILITY = 0u;
const uint AVERAGE_OFF_THE_MAP = 1u;  // taken as lit
const uint AVERAGE_IMPRECISE = 2u;    // the ray is marched instead

// The weighted average visibility between boundary positions x0 < x1 from the filtered
// basis alone (Prefiltered::look_up); with `measure_blur`, also the share of its weight
// within BLUR_ROWS of the ray's key: how much the visibility changes from the coefficients
// that far below to those as far above. (The CPU finds that difference from the ray's own
// coefficient row, Tables::blur_of; the table's rows give the same but for rounding, and
// within BLUR_ROWS of the table's ends, where they are clamped.)
uint look_up(vec4 located, float key, float x0, float x1, bool measure_blur,
             out float visibility, out float blurred) {
    visibility = 0.0;
    blurred = 0.0;
    float log2_rate = log2(located.z);
    uint lower_slice, upper_slice;
    float slice_fraction;
    neighbours(located.x, lower_slice, upper_slice, slice_fraction);
    for (uint n = 0u; n < 2u; ++n) {
        uint slice = n == 0u ? lower_slice : upper_slice;
        float share = n == 0u ? 1.0 - slice_fraction : slice_fraction;
        if (share == 0.0) {
            continue;
        }
        uvec2 range = slice_bands[slice];
        uint j, next;
        float band_fraction;
        bands_at(slice, log2_rate, j, next, band_fraction);
        float shares = 0.0;
        float dot_ = 0.0;
        for (uint k = 0u; k < 2u; ++k) {
            uint band_index = range.x + (k == 0u ? j : next);
            float band_share = k == 0u ? 1.0 - band_fraction : band_fraction;
            if (band_share == 0.0) {
                continue;
            }
            uvec2 band = bands[band_index];
            uint first_row = band.x;
            uint end_lower, start_lower;
            float end_fraction, start_fraction;
            boundary(x1, band.y, end_lower, end_fraction);
            boundary(x0, band.y, start_lower, start_fraction);
            float w_end = weight[first_row + end_lower];
            if (end_fraction != 0.0) {
                w_end += end_fraction * (weight[first_row + end_lower + 1u] - w_end);
            }
            float w_start = weight[first_row + start_lower];
            if (start_fraction != 0.0) {
                w_start += start_fraction * (weight[first_row + start_lower + 1u] - w_start);
            }
            float dw = w_end - w_start;
            // prefiltered.rs: CONDITION_LIMIT; first, as a stretch past the weights' depth
            // cap holds no weight either.
            if (w_start > 100.0 * dw) {
                return AVERAGE_IMPRECISE;
            }
            if (!(dw > 0.0)) {
                return AVERAGE_OFF_THE_MAP;
            }
            float scale = share * band_share / dw;
            // Two ends × two boundaries, in fixed slots (factor 0 when unused) so that the
            // compiler keeps them in registers.
            uint rows[4] = uint[4](0u, 0u, 0u, 0u);
            float factors[4] = float[4](0.0, 0.0, 0.0, 0.0);
            for (uint e = 0u; e < 2u; ++e) {
                uint lower = e == 0u ? end_lower : start_lower;
                float fraction = e == 0u ? end_fraction : start_fraction;
                float sign_ = e == 0u ? 1.0 : -1.0;
                for (uint h = 0u; h < 2u; ++h) {
                    uint b = lower + h;
                    float part = h == 0u ? 1.0 - fraction : fraction;
                    if (b == 0u || part == 0.0) {
                        continue;
                    }
                    uint slot = e * 2u + h;
                    rows[slot] = first_row + b;
                    factors[slot] = sign_ * scale * part * weight[first_row + b];
                }
            }
            shares += share * band_share;
            float z = warp(band_index, key);
            uint entry = uint(z * TABLE_STEPS + 0.5);
            dot_ += blend_dot(rows, factors, entry);
            if (measure_blur) {
                uint above = min(entry + BLUR_ROWS, uint(TABLE_STEPS));
                uint below = entry > BLUR_ROWS ? entry - BLUR_ROWS : 0u;
                blurred += blend_dot(rows, factors, above) - blend_dot(rows, factors, below);
            }
        }
        visibility += clamp(0.5 * shares + dot_, 0.0, shares);
    }
    return AVERAGE_VISIBILITY;
}

// Weighted average visibility between boundary positions x0 < x1: exact where the ray is
// lit or shadowed all along, else looked up, and marched where the lookup reads darker
// than the series resolves or is decided by its blur (Prefiltered::average).
uint average(vec4 located, float key, float x0, float x1, out float visibility) {
    if (uniform_visibility(located, x0, x1, visibility)) {
        return AVERAGE_VISIBILITY;
    }
    float blurred;
    uint outcome = look_up(located, key, x0, x1, true, visibility, blurred);
    if (outcome == AVERAGE_VISIBILITY
        && (blurred > BLURRED_SHARE_LIMIT || visibility < q.dark_lookup_limit)) {
        return AVERAGE_IMPRECISE;
    }
    return outcome;
}

float infinity() {
    return uintBitsToFloat(0x7f800000u);
}

// The value whose order_key is `key`, ±∞ beyond the keys' range (EpipolarMap::value_of_key).
float value_of_key(float key) {
    if (q.map_layout == PARALLEL) {
        return -key;
    }
    if (key <= -1.0) {
        return infinity();
    }
    if (key >= 1.0) {
        return -infinity();
    }
    return -key / (1.0 - abs(key)) / q.key_scale;
}

// The key that `band`'s warp takes to `z` (Warp::unwarp).
float unwarp(uint band, float z) {
    const float segment = (1.0 - 2.0 * WARP_MARGIN) / float(KNOTS - 1u);
    uint base = band * KNOTS;
    uint index = min(uint(max((z - WARP_MARGIN) / segment, 0.0)), KNOTS - 2u);
    float gap = band_knots[base + index + 1u] - band_knots[base + index];
    return band_knots[base + index] + (z - WARP_MARGIN - segment * float(index)) / segment * gap;
}

// Where rectified sample i begins along its slice.
float sample_start(uint i) {
    float step_ = q.spacing_step / SAMPLES_PER_ROW;
    if (q.reciprocal_spacing == 0u) {
        return q.spacing_first + float(i) * step_;
    }
    return 1.0 / (q.spacing_first - float(i) * step_);
}

// The stretch before a ray's end where its dominant slice's samples lie within the step's
// width of the ray's key (Prefiltered::exact_end): false where there is none; else where
// it starts, and its in-scattering in the medium that starts at `a` (a box's needs
// begin_ray; `all_lit`: every sample lit, the in-scattering left to the caller).
bool exact_end(vec4 located, float t_from, float t_end, float a, bool in_box, out float t_cut, out float scattering, out bool all_lit) {
    t_cut = t_end;
    scattering = 0.0;
    all_lit = false;
    uint lower_slice, upper_slice;
    float slice_fraction;
    neighbours(located.x, lower_slice, upper_slice, slice_fraction);
    uint slice = slice_fraction > 1.0 - slice_fraction ? upper_slice : lower_slice;
    uint j, next;
    float band_fraction;
    bands_at(slice, log2(located.z), j, next, band_fraction);
    uint band = slice_bands[slice].x + (band_fraction > 1.0 - band_fraction ? next : j);
    float z = warp(band, order_key(located.w));
    float width = EXACT_END_WIDTH / float(q.frequencies);
    float low = z + width >= 1.0 ? -infinity() : value_of_key(unwarp(band, z + width));
    float high = z - width <= 0.0 ? infinity() : value_of_key(unwarp(band, z - width));
    float s_from = located.y + located.z * t_from;
    float s_end = located.y + located.z * t_end;
    float end = sample_coordinate(s_end) * SAMPLES_PER_ROW;
    if (!(end > 0.0 && end < float(q.samples))) {
        return false;
    }
    uint last = uint(end);
    uint row = slice * q.samples;
    float value = rectified[row + last];
    if (!(low < value && value < high)) {
        return false;
    }
    uint first = uint(max(sample_coordinate(s_from) * SAMPLES_PER_ROW, 0.0));
    first = min(max(first, last >= MAX_EXACT_END_SAMPLES - 1u ? last - (MAX_EXACT_END_SAMPLES - 1u) : 0u), last);
    uint cut = last;
    while (cut > first) {
        float before = rectified[row + cut - 1u];
        if (!(low < before && before < high)) {
            break;
        }
        cut -= 1u;
    }
    float s_cut = max(sample_start(cut), s_from);
    t_cut = (s_cut - located.y) / located.z;
    all_lit = true;
    for (uint i = cut; i <= last; ++i) {
        if (!(located.w <= rectified[row + i])) {
            all_lit = false;
            break;
        }
    }
    if (all_lit) {
        return true;
    }
    // Runs of lit samples, each integrated in closed form.
    float sigma = p.extinction;
    bool in_run = false;
    float run_start = 0.0;
    for (uint i = cut; i <= last + 1u; ++i) {
        bool lit = i <= last && located.w <= rectified[row + i];
        if (lit && !in_run) {
            in_run = true;
            run_start = max(sample_start(i), s_cut);
        } else if (!lit && in_run) {
            in_run = false;
            float t0 = (run_start - located.y) / located.z;
            float t1 = ((i <= last ? sample_start(i) : s_end) - located.y) / located.z;
            scattering += in_box ? box_integrate(t0, t1, a, sigma)
                                 : exp(-sigma * (t0 - a)) * integral_exp(sigma, t1 - t0);
        }
    }
    return true;
}

// Whether a `stretch` of a ray `located` crosses fewer than `texels` texels, too few for
// the prefix sums' resolution (EpipolarMap::is_short, is_short_stretch); the projective
// layout resolves any length.
bool is_short(vec4 located, float stretch, float texels) {
    return q.map_layout != PROJECTIVE && located.z * stretch < texels;
}

// (scattering, alpha, visibility); `ok` false where the ray cannot be located.
vec3 prefiltered_sample(vec3 origin, vec3 direction, float t_start, float t_end, out bool ok) {
    vec4 located;
    ok = locate(origin, direction, located);
    if (!ok) {
        return vec3(0.0);
    }
    if (!(t_end > t_start)) {
        return vec3(0.0, 0.0, 1.0);
    }
    // Too short for the prefix sums' resolution: marched instead.
    if (is_short(located, t_end - t_start, SHORT_RAY_TEXELS)) {
        ok = false;
        return vec3(0.0);
    }
    // Nearly along the light (is_along_the_light): walked instead.
    float along = dot(direction, p.light_travel.xyz);
    if (along > 0.0 && 1.0 - along * along < ALONG_THE_LIGHT_SIN * ALONG_THE_LIGHT_SIN) {
        ok = false;
        return vec3(0.0);
    }
    float key = order_key(located.w);
    float a = t_start;
    float b = t_end;
    bool inside = true;
    if (p.box_medium != BOX_NONE) {
        begin_ray(origin, direction);
        inside = box_segment(t_start, t_end, a, b);
    }
    float visibility;
    if (!inside) {
        float x0 = sample_coordinate(located.y + located.z * t_start);
        float x1 = sample_coordinate(located.y + located.z * t_end);
        uint outcome = average(located, key, x0, x1, visibility);
        if (outcome == AVERAGE_IMPRECISE) {
            ok = false;
            return vec3(0.0);
        }
        if (outcome == AVERAGE_OFF_THE_MAP) {
            visibility = 1.0;
        }
        return vec3(0.0, 0.0, visibility);
    }
    // In a box the stretch before the medium is always subtracted (see the CPU's march).
    float from = (q.near_plane_correction != 0u || a > t_start || p.box_medium != BOX_NONE) ? a : 0.0;
    float sigma = p.extinction;
    float alpha = -expm1_accurate(-sigma * (b - a));
    // Dense fog: the first LOOKUP_DEPTH of optical depth is what counts (is_short_in_medium).
    if (is_short(located, sigma > 0.0 ? min(b - a, LOOKUP_DEPTH / sigma) : b - a, SHORT_STRETCH_TEXELS)) {
        ok = false;
        return vec3(0.0);
    }
    if (p.box_medium == BOX_NONE) {
        float unshadowed = sigma * (b - a) >= 1e-8 ? alpha / sigma : integral_exp(sigma, b - a);
        float t_cut, end_scattering;
        bool all_lit;
        bool has_end = q.exact_ray_ends != 0u && exact_end(located, from, b, a, false, t_cut, end_scattering, all_lit);
        // The end is integrated exactly, the rest looked up: unless that rest is too short
        // for a lookup of its own.
        if (has_end && (t_cut <= a || is_short(located, t_cut - from, SHORT_STRETCH_TEXELS))) {
            ok = false;
            return vec3(0.0);
        }
        float x0 = sample_coordinate(located.y + located.z * from);
        float x1 = sample_coordinate(located.y + located.z * (has_end ? t_cut : b));
        uint outcome = average(located, key, x0, x1, visibility);
        if (outcome == AVERAGE_IMPRECISE) {
            ok = false;
            return vec3(0.0);
        }
        if (outcome == AVERAGE_OFF_THE_MAP) {
            visibility = 1.0;
        }
        if (!has_end) {
            return vec3(visibility * unshadowed, alpha, visibility);
        }
        float before = integral_exp(sigma, t_cut - a);
        float after = all_lit ? unshadowed - before : end_scattering;
        float scattering = visibility * before + after;
        float weighted = unshadowed > 1e-30 ? clamp(scattering / unshadowed, 0.0, 1.0) : visibility;
        return vec3(scattering, alpha, weighted);
    }
    // Inside a box the sunlight's attenuation varies along the ray: pieces over which it
    // changes by a bounded optical depth, each its own average times its own integral
    // (box_pieces on the CPU).
    float change = sigma * box_sunward_change(a, b);
    float sunward = ceil(change / BOX_PIECE_DEPTH);
    float view = ceil(sigma * (b - a) / BOX_PIECE_VIEW_DEPTH);
    uint sunward_pieces = uint(clamp(sunward, 1.0, float(MAX_BOX_PIECES)));
    uint pieces = uint(clamp(max(sunward, view), 1.0, float(MAX_BOX_PIECES)));
    bool too_short = is_short(located, (b - a) / float(pieces), SHORT_STRETCH_TEXELS);
    // Pieces for the view ray's depth alone where they are long enough for lookups.
    if (too_short && pieces > sunward_pieces) {
        pieces = sunward_pieces;
        too_short = is_short(located, (b - a) / float(pieces), SHORT_STRETCH_TEXELS);
    }
    // A piece crossing too few texels is too short for its own lookup: marched instead.
    if (too_short) {
        ok = false;
        return vec3(0.0);
    }
    // A ray that ends on a surface inside the box may close in on it in its last piece:
    // that piece is then looked up only to the cut, or not at all.
    uint last = pieces - 1u;
    float t_last = a + (b - a) * float(last) / float(pieces);
    float last_start = last == 0u ? from : t_last;
    float t_cut, end_scattering;
    bool all_lit;
    bool has_end = q.exact_ray_ends != 0u && b >= t_end
        && exact_end(located, last_start, b, a, true, t_cut, end_scattering, all_lit);
    uint looked_up = pieces;
    float last_end = b;
    if (has_end) {
        if (t_cut <= t_last) {
            if (last == 0u) {
                ok = false;
                return vec3(0.0);
            }
            looked_up = last;
            last_end = t_last;
        } else {
            if (is_short(located, t_cut - last_start, SHORT_STRETCH_TEXELS)) {
                ok = false;
                return vec3(0.0);
            }
            last_end = t_cut;
        }
    }
    // A ray lit or shadowed all along is exact; pieces are not tested one by one
    // (Prefiltered::average_pieces).
    float whole;
    float x_from = sample_coordinate(located.y + located.z * from);
    float x_last = sample_coordinate(located.y + located.z * last_end);
    bool uniform_ = uniform_visibility(located, x_from, x_last, whole);
    // A stretch decided by its blur is marched, as a whole (Prefiltered::average_pieces).
    if (!uniform_) {
        float unused, blurred;
        if (look_up(located, key, x_from, x_last, true, unused, blurred) == AVERAGE_VISIBILITY
            && blurred > BLURRED_SHARE_LIMIT) {
            ok = false;
            return vec3(0.0);
        }
    }
    float scattering = 0.0;
    float unshadowed = 0.0;
    // The looked-up pieces' light; `scattering` is what of it they let through until the
    // exact end is added.
    float looked_up_light = 0.0;
    for (uint k = 0u; k < pieces; ++k) {
        float t0 = a + (b - a) * float(k) / float(pieces);
        float t1 = a + (b - a) * float(k + 1u) / float(pieces);
        float piece = box_integrate(t0, t1, a, sigma);
        unshadowed += piece;
        if (k >= looked_up) {
            continue;
        }
        float until = has_end && k == last ? last_end : t1;
        float x0 = sample_coordinate(located.y + located.z * (k == 0u ? from : t0));
        float x1 = sample_coordinate(located.y + located.z * until);
        float v = whole;
        float unused;
        uint outcome = uniform_ ? AVERAGE_VISIBILITY
                                : look_up(located, key, x0, x1, false, v, unused);
        if (outcome == AVERAGE_IMPRECISE) {
            ok = false;
            return vec3(0.0);
        }
        if (outcome == AVERAGE_OFF_THE_MAP) {
            v = 1.0;
        }
        float light = has_end && k == last ? box_integrate(t0, until, a, sigma) : piece;
        scattering += v * light;
        looked_up_light += light;
    }
    // A ray the lookups read nearly dark is marched instead (Prefiltered::average_pieces).
    if (!uniform_ && looked_up_light > 0.0
        && scattering < q.dark_lookup_limit * looked_up_light) {
        ok = false;
        return vec3(0.0);
    }
    if (has_end) {
        scattering += all_lit ? box_integrate(t_cut, b, a, sigma) : end_scattering;
    }
    visibility = unshadowed > 1e-30 ? clamp(scattering / unshadowed, 0.0, 1.0) : 1.0;
    return vec3(scattering, alpha, visibility);
}

bool near_epipole(vec2 pixel) {
    for (uint i = 0u; i < q.epipole_count; ++i) {
        vec2 e = i == 0u ? q.epipoles.xy : q.epipoles.zw;
        if (abs(pixel.x - e.x) <= q.block && abs(pixel.y - e.y) <= q.block) {
            return true;
        }
    }
    return false;
}

vec3 shade_sample(vec2 pixel, vec3 origin, vec3 direction, float t_start, float t_end) {
    if (near_epipole(pixel)) {
        return fallback_sample(origin, direction, t_start, t_end);
    }
    bool ok;
    vec3 s = prefiltered_sample(origin, direction, t_start, t_end, ok);
    return ok ? s : fallback_sample(origin, direction, t_start, t_end);
}

// Adaptive shading (core/src/adaptive.rs, in the GPU's own order): a coarse grid of every
// fourth pixel each way is shaded; then, at steps 4 and 2, the midpoints between resolved
// pixels (first those on the grid's lines, then the cells' centres) take the mean of a
// pair of resolved neighbours either side where the pair agrees, or lies on a smooth ramp
// with the points beyond, and the pixel sees their surface. The others are listed, and
// shaded by an indirect dispatch over the list, so that shading threads run side by side
// rather than among threads that only interpolated.
const uint FULL = 0u;
const uint COARSE = 1u;
const uint EDGES = 2u;
const uint CENTRES = 3u;
const uint ARGS = 4u;
const uint LISTED = 5u;
const uint COARSE_STEP = 4u;
const uint GROUP_SIZE = 64u;
// The least maximum workgroup count along x that Vulkan guarantees.
const uint MAX_GROUPS_X = 65535u;

layout(push_constant) uniform Adaptive {
    uint phase;
    uint step;          // EDGES, CENTRES: the resolved grid's step
    float tolerance;
    uint perspective;   // reaches compare in inverse distance (else distance)
} a;

// Set up by adaptive_floor.comp after COARSE.
#define ADAPTIVE_STATE_BINDING 17
#include "adaptive_state.glsl"

layout(std430, binding = 18) buffer ShadeList { uint shade_list[]; };

float reach_coordinate(float depth) {
    float reach = min(depth, p.max_distance);
    return a.perspective != 0u ? 1.0 / reach : reach;
}

// adaptive.rs: SurfaceCoordinate::holds.
bool on_surface(float expected, float reach) {
    if (a.perspective != 0u) {
        float product = expected * reach;
        return abs(1.0 - product) <= EDGE_DEPTH_SPREAD * product;
    }
    return abs(expected - reach) <= EDGE_DEPTH_SPREAD * reach;
}

// Writes pixel `id` as a blend of its neighbours whose rays end at `coordinate`, where
// its own ray ends on that surface (adaptive.rs: Interpolation::on_surface).
bool blended(ivec2 id, vec4 volume, float visibility, float coordinate) {
    float surface;
    // Not NaN, nor infinite: a reach of 0 (a resolved pixel's buffer never written) would
    // hold any surface.
    if (isnan(coordinate) || isinf(coordinate) || !uniform_pixel_surface(uvec2(id), surface)) {
        return false;
    }
    float depth = surface < 0.0 ? p.max_distance : surface;
    if (!on_surface(coordinate, min(depth, p.max_distance))) {
        return false;
    }
    uint index = uint(id.y) * p.width + uint(id.x);
    volume_out[index] = volume;
    visibility_out[index] = visibility;
    depth_out[index] = depth;
    return true;
}

bool in_image(ivec2 pixel) {
    return pixel.x >= 0 && pixel.y >= 0 && pixel.x < int(p.width) && pixel.y < int(p.height);
}

uint index_of(ivec2 pixel) {
    return uint(pixel.y) * p.width + uint(pixel.x);
}

// The spreads a blend allows (adaptive.rs: Agreement::allowed_spreads): RGBA relative to
// the blend or the floor, whichever is larger.
vec4 allowed_spreads(vec4 volume) {
    return a.tolerance * max(abs(volume), state.floor_rgba);
}

// Pixel `id` as the mean of the pair at ±`offset` where they agree (adaptive.rs:
// Agreement::blend). Comparisons are written so that NaN disagrees.
bool pair_mean(ivec2 id, ivec2 offset) {
    ivec2 n0 = id - offset;
    ivec2 n1 = id + offset;
    if (!in_image(n0) || !in_image(n1)) {
        return false;
    }
    vec4 v0 = volume_out[index_of(n0)];
    vec4 v1 = volume_out[index_of(n1)];
    float vis0 = visibility_out[index_of(n0)];
    float vis1 = visibility_out[index_of(n1)];
    vec4 volume = v0 + 0.5 * (v1 - v0);
    bool agree = all(lessThanEqual(abs(v1 - v0), allowed_spreads(volume)))
        && abs(vis1 - vis0) <= a.tolerance;
    if (!agree) {
        return false;
    }
    float c0 = reach_coordinate(depth_out[index_of(n0)]);
    float c1 = reach_coordinate(depth_out[index_of(n1)]);
    return blended(id, volume, vis0 + 0.5 * (vis1 - vis0), c0 + 0.5 * (c1 - c0));
}

// Pixel `id` as the mean of the pair at ±`offset` where it and the points beyond, at
// ±3·`offset`, lie on a smooth ramp: each step differs from the one before by at most
// what the pair may spread (adaptive.rs: Agreement::blend_on_ramp).
bool ramp_mean(ivec2 id, ivec2 offset) {
    ivec2 points[4] = ivec2[4](id - 3 * offset, id - offset, id + offset, id + 3 * offset);
    if (!in_image(points[0]) || !in_image(points[3])) {
        return false;
    }
    vec4 v[4];
    float vis[4];
    for (int i = 0; i < 4; ++i) {
        v[i] = volume_out[index_of(points[i])];
        vis[i] = visibility_out[index_of(points[i])];
    }
    vec4 volume = v[1] + 0.5 * (v[2] - v[1]);
    vec4 allowed = allowed_spreads(volume);
    vec4 s0 = v[1] - v[0];
    vec4 s1 = v[2] - v[1];
    vec4 s2 = v[3] - v[2];
    float w0 = vis[1] - vis[0];
    float w1 = vis[2] - vis[1];
    float w2 = vis[3] - vis[2];
    bool smooth_ramp = all(lessThanEqual(abs(s1 - s0), allowed))
        && all(lessThanEqual(abs(s2 - s1), allowed))
        && abs(w1 - w0) <= a.tolerance
        && abs(w2 - w1) <= a.tolerance
        && !isnan(depth_out[index_of(points[0])])
        && !isnan(depth_out[index_of(points[3])]);
    if (!smooth_ramp) {
        return false;
    }
    float c1 = reach_coordinate(depth_out[index_of(points[1])]);
    float c2 = reach_coordinate(depth_out[index_of(points[2])]);
    return blended(id, volume, vis[1] + 0.5 * (vis[2] - vis[1]), c1 + 0.5 * (c2 - c1));
}

// Pixel `id` from the pair at ±`offset` (or, where `other` is not zero, the pair at
// ±`other`), on a ramp if not alone; listed to be shaded where none serves.
void resolve(ivec2 id, ivec2 offset, ivec2 other) {
    bool both = other != ivec2(0);
    bool done = pair_mean(id, offset)
        || (both && pair_mean(id, other))
        || ramp_mean(id, offset)
        || (both && ramp_mean(id, other));
    if (!done) {
        shade_list[atomicAdd(state.listed, 1u)] = index_of(id);
    }
}

void main() {
    uvec2 gid = gl_GlobalInvocationID.xy;
    // One call of shade_pixel for every phase that shades: lavapipe inlines each call,
    // and with three the shader ran three times as slowly even where they were skipped.
    uvec2 shaded_id = gid;
    bool shade = false;
    if (a.phase == FULL) {
        shade = gid.x < p.width && gid.y < p.height;
    } else if (a.phase == COARSE) {
        shaded_id = gid * COARSE_STEP;
        shade = shaded_id.x < p.width && shaded_id.y < p.height;
    } else if (a.phase == EDGES) {
        // Two candidates a cell: the midpoints of its top and left sides.
        int s = int(a.step);
        int h = s / 2;
        ivec2 cell = ivec2(gid.x / 2u, gid.y);
        bool vertical = (gid.x & 1u) != 0u;
        ivec2 id = cell * s + (vertical ? ivec2(0, h) : ivec2(h, 0));
        if (in_image(id)) {
            resolve(id, vertical ? ivec2(0, h) : ivec2(h, 0), ivec2(0));
        }
    } else if (a.phase == CENTRES) {
        int s = int(a.step);
        int h = s / 2;
        ivec2 id = ivec2(gid) * s + ivec2(h);
        if (in_image(id)) {
            resolve(id, ivec2(h, 0), ivec2(0, h));
        }
    } else if (a.phase == ARGS) {
        // One invocation.
        if (gl_LocalInvocationIndex == 0u) {
            uint count = state.listed;
            uint groups = (count + GROUP_SIZE - 1u) / GROUP_SIZE;
            state.to_shade = count;
            state.shaded += count;
            state.listed = 0u;
            uint x = max(min(groups, MAX_GROUPS_X), 1u);
            state.args = uvec4(x, (groups + x - 1u) / x, 1u, 0u);
        }
    } else if (a.phase == LISTED) {
        uint group = gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x;
        uint i = group * GROUP_SIZE + gl_LocalInvocationIndex;
        if (i < state.to_shade) {
            uint index = shade_list[i];
            shaded_id = uvec2(index % p.width, index / p.width);
            shade = true;
        }
    }
    if (shade) {
        shade_pixel(shaded_id);
    }
}
