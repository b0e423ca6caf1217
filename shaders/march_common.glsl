// The reference ray march (core/src/reference.rs) and the per-pixel loop of the CPU frame
// (core/src/render.rs, shade_pixels), shared by the shaders that write the layers: they
// define `shade_sample` and call `shade_output_pixel` from main.
#include "common.glsl"


layout(std430, binding = 0) readonly buffer Params {
    mat4 world_from_camera;
    mat4 texel_from_world;
    mat4 cube_from_world;
    vec4 origin0;   // camera-space ray origin at pixel (0, 0), and its steps per pixel
    vec4 origin_dx;
    vec4 origin_dy;
    vec4 dir0;      // camera-space (unnormalized) ray direction, likewise
    vec4 dir_dx;
    vec4 dir_dy;
    vec4 tint;      // albedo · σt · E
    vec4 light_travel;
    vec4 towards_sun; // in cube space, per world unit
    float clip_start;
    float max_distance;
    float extinction;
    float bias;
    float anisotropy;
    uint isotropic;
    uint box_medium; // BOX_NONE, BOX_ATTENUATING or BOX_UNATTENUATING
    uint steps;
    uint width;
    uint height;
    uint full_width;
    uint full_height;
    uint stride;
    uint supersampling;
    uint map_size;
    uint dark_walks; // walks still dark at e^−10 go on (reference.rs: DARK_WALK_SHARE)
    float texel_size; // world size of a shadow-map texel along its larger side
    uint shadowed_ends; // rays end their light before an unlit side (shadowed_end.rs)
} p;

// core/src/gpu/march.rs: BoxKind. In a box whose sunlight is not attenuated (a light that
// casts no shadows), the sunward depth is 0 everywhere.
const uint BOX_NONE = 0u;
const uint BOX_ATTENUATING = 1u;
const uint BOX_UNATTENUATING = 2u;

layout(std430, binding = 1) readonly buffer ShadowDepth { float shadow_depth[]; };
// Ray distance to the first surface per depth sample; negative for background.
layout(std430, binding = 2) readonly buffer Surfaces { float surfaces[]; };
// Read back by adaptive shading (prefiltered.comp), which blends shaded neighbours.
layout(std430, binding = 3) buffer Volume { vec4 volume_out[]; };
layout(std430, binding = 4) buffer Visibility { float visibility_out[]; };
layout(std430, binding = 5) buffer Depth { float depth_out[]; };

vec3 texel_origin;
vec3 texel_step;
vec3 cube_origin;
vec3 cube_step;

bool lit(float t) {
    vec3 texel = texel_origin + texel_step * t;
    float size = float(p.map_size);
    if (!(texel.x >= 0.0 && texel.y >= 0.0 && texel.x < size && texel.y < size)) {
        return true;
    }
    uint index = uint(texel.y) * p.map_size + uint(texel.x);
    return texel.z <= shadow_depth[index] + p.bias;
}

float average_visibility(float t_start, float t_end) {
    uint n = p.steps;
    float dt = (t_end - t_start) / float(n);
    uint lit_steps = 0;
    for (uint i = 0; i < n; ++i) {
        if (lit(t_start + (float(i) + 0.5) * dt)) {
            lit_steps += 1;
        }
    }
    return float(lit_steps) / float(n);
}

// V̄: in-scattering over what it would be unshadowed (reference.rs, weighted_visibility).
// A ray lit at every step has exactly 1, as on the CPU, whatever order the GPU sums in.
float weighted_visibility(float scattering, float unshadowed, bool shadowed, float t_start, float t_end) {
    if (!(unshadowed > 0.0)) {
        return average_visibility(t_start, t_end);
    }
    return shadowed ? clamp(scattering / unshadowed, 0.0, 1.0) : 1.0;
}

// x: scattering, y: alpha, z: visibility.
vec3 march_unbounded(float t_start, float t_end) {
    uint n = p.steps;
    float dt = (t_end - t_start) / float(n);
    float sigma = p.extinction;
    float decay = exp(-sigma * dt);
    float per_step = integral_exp(sigma, dt);
    float transmittance = 1.0;
    precise float scattering = 0.0;
    precise float unshadowed = 0.0;
    bool shadowed = false;
    for (uint i = 0; i < n; ++i) {
        if (lit(t_start + (float(i) + 0.5) * dt)) {
            scattering += transmittance;
        } else {
            shadowed = true;
        }
        unshadowed += transmittance;
        transmittance *= decay;
    }
    float visibility = weighted_visibility(scattering, unshadowed, shadowed, t_start, t_end);
    return vec3(scattering * per_step, -expm1_accurate(-sigma * (t_end - t_start)), visibility);
}

bool box_clip(out float near, out float far) {
    near = -BIG;
    far = BIG;
    for (int axis = 0; axis < 3; ++axis) {
        float o = cube_origin[axis];
        float d = cube_step[axis];
        if (abs(d) < 1e-30) {
            if (abs(o) > 1.0) {
                return false;
            }
            continue;
        }
        float t0 = (-1.0 - o) / d;
        float t1 = (1.0 - o) / d;
        near = max(near, min(t0, t1));
        far = min(far, max(t0, t1));
    }
    return near < far;
}

// The ray's stretch [a, b] of [t_start, t_end] inside the box, if it has one
// (reference.rs, medium_segment). Needs begin_ray.
bool box_segment(float t_start, float t_end, out float a, out float b) {
    float near, far;
    bool hit = box_clip(near, far);
    a = max(near, t_start);
    b = min(far, t_end);
    return hit && b > a;
}

float sunward_depth(vec3 cube_point) {
    if (p.box_medium == BOX_UNATTENUATING) {
        return 0.0;
    }
    float depth = BIG;
    for (int axis = 0; axis < 3; ++axis) {
        float s = p.towards_sun[axis];
        if (s != 0.0) {
            float wall = s > 0.0 ? 1.0 : -1.0;
            depth = min(depth, (wall - cube_point[axis]) / s);
        }
    }
    return max(depth, 0.0);
}

vec3 march_box(float t_start, float t_end) {
    float a, b;
    if (!box_segment(t_start, t_end, a, b)) {
        return vec3(0.0, 0.0, average_visibility(t_start, t_end));
    }
    uint n = p.steps;
    float dt = (b - a) / float(n);
    float sigma = p.extinction;
    float depth_before = sunward_depth(cube_origin + cube_step * a);
    precise float scattering = 0.0;
    precise float unshadowed = 0.0;
    bool shadowed = false;
    for (uint i = 0; i < n; ++i) {
        float t0 = a + float(i) * dt;
        float depth_after = sunward_depth(cube_origin + cube_step * (t0 + dt));
        float slope = (depth_after - depth_before) / dt;
        float step_weight = stretch_integral(sigma, a, t0, t0 + dt, depth_before, depth_after, slope);
        if (lit(t0 + 0.5 * dt)) {
            scattering += step_weight;
        } else {
            shadowed = true;
        }
        unshadowed += step_weight;
        depth_before = depth_after;
    }
    float visibility = weighted_visibility(scattering, unshadowed, shadowed, t_start, t_end);
    return vec3(scattering, -expm1_accurate(-sigma * (b - a)), visibility);
}

float phase(vec3 direction) {
    if (p.isotropic != 0u) {
        return 1.0 / (4.0 * PI);
    }
    float g = p.anisotropy;
    float cos_theta = dot(p.light_travel.xyz, -direction);
    float g2 = g * g;
    float denominator = 1.0 + g2 - 2.0 * g * cos_theta;
    return (1.0 - g2) / (4.0 * PI * denominator * sqrt(denominator));
}


// Sets the per-ray state the march functions read.
void begin_ray(vec3 origin, vec3 direction) {
    texel_origin = (p.texel_from_world * vec4(origin, 1.0)).xyz;
    texel_step = mat3(p.texel_from_world) * direction;
    if (p.box_medium != BOX_NONE) {
        cube_origin = (p.cube_from_world * vec4(origin, 1.0)).xyz;
        cube_step = mat3(p.cube_from_world) * direction;
    }
}

// The reference march of one ray: (scattering, alpha, visibility).
vec3 reference_sample(vec3 origin, vec3 direction, float t_start, float t_end) {
    if (!(t_end > t_start)) {
        return vec3(0.0, 0.0, 1.0);
    }
    begin_ray(origin, direction);
    return p.box_medium != BOX_NONE ? march_box(t_start, t_end) : march_unbounded(t_start, t_end);
}

// core/src/reference.rs: NEGLIGIBLE_STRETCH.
const float NEGLIGIBLE_STRETCH = 1e-3;

// The ray's sunward depth ℓ(t) = min over the walls the sun points at of x + y·t, and the
// points in (t0, t1) where the minimum may switch, sorted after t0 and before t1: `count`
// stretches, as BoxRay::for_each_line. Needs begin_ray.
void box_lines(float t0, float t1, out vec2 lines[3], out float cuts[5], out uint count) {
    bool finite_line[3];
    for (int axis = 0; axis < 3; ++axis) {
        float s = p.box_medium == BOX_UNATTENUATING ? 0.0 : p.towards_sun[axis];
        finite_line[axis] = s != 0.0;
        if (p.box_medium == BOX_UNATTENUATING && axis == 0) {
            lines[axis] = vec2(0.0);
        } else if (s != 0.0) {
            float wall = s > 0.0 ? 1.0 : -1.0;
            lines[axis] = vec2((wall - cube_origin[axis]) / s, -cube_step[axis] / s);
        } else {
            lines[axis] = vec2(BIG, 0.0);
        }
    }
    cuts = float[5](t0, t1, t1, t1, t1);
    count = 1u;
    for (int i = 0; i < 3; ++i) {
        for (int k = i + 1; k < 3; ++k) {
            if (finite_line[i] && finite_line[k] && lines[i].y != lines[k].y) {
                float t = (lines[k].x - lines[i].x) / (lines[i].y - lines[k].y);
                if (t > t0 && t < t1) {
                    cuts[count] = t;
                    count += 1u;
                }
            }
        }
    }
    cuts[count] = t1;
    for (uint i = 1u; i <= count; ++i) {
        for (uint k = i; k > 0u && cuts[k - 1u] > cuts[k]; --k) {
            float swap = cuts[k];
            cuts[k] = cuts[k - 1u];
            cuts[k - 1u] = swap;
        }
    }
}

// The line ℓ follows over a stretch: the lowest at its middle (a wall the sun grazes has
// a nearly vertical line), as BoxRay::for_each_line.
vec2 box_line_over(vec2 lines[3], float p0, float p1) {
    float middle = 0.5 * (p0 + p1);
    vec2 lowest = lines[0];
    for (int axis = 1; axis < 3; ++axis) {
        if (lines[axis].x + lines[axis].y * middle < lowest.x + lowest.y * middle) {
            lowest = lines[axis];
        }
    }
    return lowest;
}

// ∫ e^(−σ·ℓ(t)) · e^(−σ·(t − a)) dt over [t0, t1] inside the box, exactly (ℓ is piecewise
// linear), as BoxRay::integrate. Needs begin_ray.
float box_integrate(float t0, float t1, float a, float sigma) {
    vec2 lines[3];
    float cuts[5];
    uint count;
    box_lines(t0, t1, lines, cuts, count);
    float total = 0.0;
    for (uint i = 0u; i < count; ++i) {
        float p0 = cuts[i];
        float p1 = cuts[i + 1u];
        if (!(p1 > p0)) {
            continue;
        }
        vec2 line = box_line_over(lines, p0, p1);
        total += stretch_integral(sigma, a, p0, p1, max(line.x + line.y * p0, 0.0),
                                  max(line.x + line.y * p1, 0.0), line.y);
    }
    return total;
}

// How far ℓ rises and falls over [t0, t1], leaving out stretches shorter than
// NEGLIGIBLE_STRETCH of it, as BoxRay::sunward_change. Needs begin_ray.
float box_sunward_change(float t0, float t1) {
    vec2 lines[3];
    float cuts[5];
    uint count;
    box_lines(t0, t1, lines, cuts, count);
    float shortest = NEGLIGIBLE_STRETCH * (t1 - t0);
    float change = 0.0;
    for (uint i = 0u; i < count; ++i) {
        float p0 = cuts[i];
        float p1 = cuts[i + 1u];
        if (p1 - p0 > shortest) {
            change += abs(box_line_over(lines, p0, p1).y) * (p1 - p0);
        }
    }
    return change;
}

// What walk_lit sums over each lit part of a ray.
const uint WALK_UNBOUNDED = 0u; // e^(−σ(t − origin)) integrated
const uint WALK_BOX = 1u;       // box_integrate from origin
const uint WALK_LENGTH = 2u;    // its length

// The `mode` weight of the lit part [t0, t1] of a ray.
float lit_weight(float t0, float t1, uint mode, float origin) {
    float sigma = p.extinction;
    if (mode == WALK_UNBOUNDED) {
        return exp(-sigma * (t0 - origin)) * integral_exp(sigma, t1 - t0);
    } else if (mode == WALK_BOX) {
        return box_integrate(t0, t1, origin, sigma);
    }
    return t1 - t0;
}

// In a nearly dark frame, a walk that has seen less than this share of its unshadowed
// light by `enough` goes on to `farthest` (reference.rs: DARK_WALK_SHARE, WalkEnd).
const float DARK_WALK_SHARE = 0.01;

// Walks the shadow map's texels along the ray over [t_start, t_end] (reference.rs,
// Marcher::lit_spans), each crossing's lit part found where the ray's light depth meets
// the texel's occluder, and sums the lit parts' `mode` weights; stops past `enough`, or
// while what it has weighed is under DARK_WALK_SHARE of the unshadowed weight, past
// `farthest`. Lit parts of consecutive texels are joined before they are weighed, as on
// the CPU: each weight takes an exponential or two. Off the map counts as lit. Needs
// begin_ray.
float walk_lit(float t_start, float t_end, float enough, float farthest, uint mode,
               float origin) {
    vec3 start = texel_origin + texel_step * t_start;
    vec3 end = texel_origin + texel_step * t_end;
    ivec2 cell = ivec2(floor(start.xy));
    vec2 next = vec2(BIG);
    vec2 delta = vec2(BIG);
    ivec2 direction = ivec2(0);
    for (int axis = 0; axis < 2; ++axis) {
        float o = texel_origin[axis];
        float d = texel_step[axis];
        if (d != 0.0) {
            next[axis] = (float(cell[axis] + (d > 0.0 ? 1 : 0)) - o) / d;
            delta[axis] = 1.0 / abs(d);
            direction[axis] = d > 0.0 ? 1 : -1;
        }
    }
    float cells = min(ceil(abs(end.x - start.x)) + ceil(abs(end.y - start.y)) + 2.0, 1e7);
    int size = int(p.map_size);
    float total = 0.0;
    // The lit part not yet weighed, extended while the next texel's lit part joins it.
    bool pending = false;
    float pending_from = 0.0;
    float pending_to = 0.0;
    float t = t_start;
    for (uint i = 0u; i < uint(cells); ++i) {
        float leave = max(min(min(next.x, next.y), t_end), t);
        float lit_from = t;
        float lit_to = leave;
        if (cell.x >= 0 && cell.y >= 0 && cell.x < size && cell.y < size) {
            float threshold = shadow_depth[uint(cell.y) * p.map_size + uint(cell.x)] + p.bias;
            if (texel_step.z == 0.0) {
                if (!(texel_origin.z <= threshold)) {
                    lit_to = t;
                }
            } else {
                float meet = (threshold - texel_origin.z) / texel_step.z;
                if (texel_step.z > 0.0) {
                    lit_to = min(meet, leave);
                } else {
                    lit_from = max(meet, t);
                }
            }
        }
        if (lit_to > lit_from) {
            if (pending && lit_from <= pending_to) {
                pending_to = max(pending_to, lit_to);
            } else {
                if (pending) {
                    total += lit_weight(pending_from, pending_to, mode, origin);
                }
                pending = true;
                pending_from = lit_from;
                pending_to = lit_to;
            }
        }
        if (leave >= t_end || leave > farthest
            || (leave > enough
                && !(total < DARK_WALK_SHARE * lit_weight(origin, leave, mode, origin)))) {
            break;
        }
        if (next.y < next.x) {
            cell.y += direction.y;
            next.y += delta.y;
        } else {
            cell.x += direction.x;
            next.x += delta.x;
        }
        t = leave;
    }
    if (pending) {
        total += lit_weight(pending_from, pending_to, mode, origin);
    }
    return total;
}

// Where a walk from `t` on may stop: the rest adds less than e^−10 of its light
// (reference.rs: WALK_DEPTH).
float walk_enough(float t) {
    return p.extinction > 0.0 ? t + 10.0 / p.extinction : BIG;
}

// Where a walk from `t` stops in any case: at `walk_enough`, or in a nearly dark frame
// at e^−20 (reference.rs: DARK_WALK_DEPTH, WalkEnd::at).
float walk_farthest(float t) {
    if (p.dark_walks == 0u) {
        return walk_enough(t);
    }
    return p.extinction > 0.0 ? t + 20.0 / p.extinction : BIG;
}

// Exact single scattering outside any box (reference.rs, Marcher::walk_texels).
vec3 walk_texels(float t_start, float t_end) {
    float sigma = p.extinction;
    float scattering = walk_lit(t_start, t_end, walk_enough(t_start), walk_farthest(t_start),
                                WALK_UNBOUNDED, t_start);
    float unshadowed = integral_exp(sigma, t_end - t_start);
    float alpha = -expm1_accurate(-sigma * (t_end - t_start));
    return vec3(scattering, alpha, clamp(scattering / unshadowed, 0.0, 1.0));
}

// The walk in a box (reference.rs, Marcher::walk_box): the stretch inside it, each lit
// part attenuated through the box; a ray that misses it gets the fraction that is lit.
vec3 walk_box(float t_start, float t_end) {
    float a, b;
    if (!box_segment(t_start, t_end, a, b)) {
        float lit = walk_lit(t_start, t_end, BIG, BIG, WALK_LENGTH, t_start);
        return vec3(0.0, 0.0, clamp(lit / (t_end - t_start), 0.0, 1.0));
    }
    float sigma = p.extinction;
    float scattering = walk_lit(a, b, walk_enough(a), walk_farthest(a), WALK_BOX, a);
    float unshadowed = box_integrate(a, b, a, sigma);
    float visibility;
    if (unshadowed > 0.0) {
        visibility = clamp(scattering / unshadowed, 0.0, 1.0);
    } else {
        visibility = clamp(walk_lit(t_start, t_end, BIG, BIG, WALK_LENGTH, t_start) / (t_end - t_start), 0.0, 1.0);
    }
    return vec3(scattering, -expm1_accurate(-sigma * (b - a)), visibility);
}

// A fast method's fallback (reference.rs, Marcher::march_fallback): the exact walk.
vec3 fallback_sample(vec3 origin, vec3 direction, float t_start, float t_end) {
    if (!(t_end > t_start)) {
        return vec3(0.0, 0.0, 1.0);
    }
    begin_ray(origin, direction);
    return p.box_medium != BOX_NONE ? walk_box(t_start, t_end) : walk_texels(t_start, t_end);
}

// Relative spread of a pixel's depth samples below which no edge runs through it
// (render.rs: EDGE_DEPTH_SPREAD).
const float EDGE_DEPTH_SPREAD = 0.02;

// What one depth sample contributes; defined by the shader that includes this file.
vec3 shade_sample(vec2 pixel, vec3 origin, vec3 direction, float t_start, float t_end);

// The unlit side of the surface a ray ends on (core/src/shadowed_end.rs).
const float SAME_SURFACE_SPREAD = 0.25;
const float MIN_FACING = 0.02;
const float TEXEL_REACH = 0.70710678;

// Depth sample g's ray distance; BIG for background and outside the image.
float sample_distance(ivec2 g) {
    int width = int(p.full_width * p.supersampling);
    int height = int(p.full_height * p.supersampling);
    if (g.x < 0 || g.y < 0 || g.x >= width || g.y >= height) {
        return BIG;
    }
    float distance = surfaces[g.y * width + g.x];
    return distance < 0.0 ? BIG : distance;
}

// The slope of the distance towards the nearer neighbour along `axis`, per pixel, and
// which one it is (+1 after, −1 before); false beyond SAME_SURFACE_SPREAD
// (DepthSamples::surface).
bool nearer_slope(ivec2 g, ivec2 axis, float distance, out float slope, out float side) {
    float after = sample_distance(g + axis) - distance;
    float before = distance - sample_distance(g - axis);
    bool after_nearer = abs(after) <= abs(before);
    slope = after_nearer ? after : before;
    side = after_nearer ? 1.0 : -1.0;
    bool near = abs(slope) <= SAME_SURFACE_SPREAD * distance;
    slope *= float(p.supersampling);
    return near;
}

// The point at continuous pixel coordinates `pixel` and ray distance t, relative to the
// camera's position.
vec3 relative_point(vec2 pixel, float t) {
    mat3 rotation = mat3(p.world_from_camera);
    vec3 origin_cam = p.origin0.xyz + pixel.x * p.origin_dx.xyz + pixel.y * p.origin_dy.xyz;
    vec3 dir_cam = p.dir0.xyz + pixel.x * p.dir_dx.xyz + pixel.y * p.dir_dy.xyz;
    return rotation * origin_cam + normalize(rotation * dir_cam) * t;
}

// Whether the camera sees the side of the surface at `pixel` that faces away from the
// light, in closed form (DepthSamples::unlit_side_seen, FacingTerms).
bool unlit_side_seen(vec2 pixel, float t, vec2 slopes) {
    mat3 rotation = mat3(p.world_from_camera);
    vec3 l = p.light_travel.xyz;
    float along_light;
    float camera_side;
    if (p.dir_dx.xyz == vec3(0.0) && p.dir_dy.xyz == vec3(0.0)) {
        vec3 o1 = rotation * p.origin_dx.xyz;
        vec3 o2 = rotation * p.origin_dy.xyz;
        vec3 view = normalize(rotation * p.dir0.xyz);
        camera_side = dot(cross(o1, o2), view);
        along_light = dot(cross(o1, o2), l) + slopes.y * dot(cross(o1, view), l)
            + slopes.x * dot(cross(view, o2), l);
    } else {
        vec3 d0 = rotation * p.dir0.xyz;
        vec3 d1 = rotation * p.dir_dx.xyz;
        vec3 d2 = rotation * p.dir_dy.xyz;
        vec3 across_down = cross(d1, d2);
        float both = dot(across_down, l);
        float m1 = dot(cross(d1, d0), l) + pixel.y * both;
        float m2 = dot(cross(d0, d2), l) + pixel.x * both;
        vec3 d = d0 + pixel.x * d1 + pixel.y * d2;
        float dd = dot(d, d);
        camera_side = dot(across_down, d0);
        along_light = t * (both * dd - dot(d, d2) * m1 - dot(d, d1) * m2)
            + dd * (slopes.y * m1 + slopes.x * m2);
    }
    return along_light * camera_side < 0.0;
}

// Whether the map's light depth at world `point` is within the bias and `slope` of its.
bool map_holds_within(vec3 point, float slope) {
    vec3 texel = (p.texel_from_world * vec4(point, 1.0)).xyz;
    float size = float(p.map_size);
    if (!(texel.x >= 0.0 && texel.y >= 0.0 && texel.x < size && texel.y < size)) {
        return false;
    }
    float stored = shadow_depth[uint(texel.y) * p.map_size + uint(texel.x)];
    return abs(texel.z - stored) <= p.bias + slope;
}

// Where the light of a ray through `pixel` ends (shadowed_end.rs: lit_end): `t_end`
// less the tail the shadow map's bias would light behind the unlit side of the surface
// the ray ends on.
float lit_end(vec2 pixel, vec3 origin, vec3 direction, float t_start, float t_end) {
    if (p.shadowed_ends == 0u || !(t_end > t_start && t_end < p.max_distance)) {
        return t_end;
    }
    float ss = float(p.supersampling);
    ivec2 last = ivec2(int(p.full_width * p.supersampling) - 1,
                       int(p.full_height * p.supersampling) - 1);
    ivec2 g = clamp(ivec2(floor(pixel * ss)), ivec2(0), last);
    float t = sample_distance(g);
    vec2 slopes;
    vec2 sides;
    if (!(t < BIG) || !nearer_slope(g, ivec2(1, 0), t, slopes.x, sides.x)
        || !nearer_slope(g, ivec2(0, 1), t, slopes.y, sides.y)) {
        return t_end;
    }
    vec2 centre_pixel = (vec2(g) + 0.5) / ss;
    if (!unlit_side_seen(centre_pixel, t, slopes)) {
        return t_end;
    }
    vec3 end = origin + direction * t_end;
    if (!map_holds_within(end, TEXEL_REACH * p.texel_size / MIN_FACING)) {
        return t_end;
    }
    vec2 steps = sides / ss;
    vec3 centre = relative_point(centre_pixel, t);
    vec3 after = relative_point(centre_pixel + vec2(steps.x, 0.0), t + slopes.x * steps.x);
    vec3 below = relative_point(centre_pixel + vec2(0.0, steps.y), t + slopes.y * steps.y);
    vec3 across = (after - centre) * sides.x;
    vec3 down = (below - centre) * sides.y;
    vec3 normal = cross(across, down);
    float length_n = length(normal);
    if (!(length_n > 0.0 && length_n < BIG)) {
        return t_end;
    }
    normal /= length_n;
    float cos_light = dot(normal, p.light_travel.xyz);
    if (!(dot(normal, direction) * cos_light < 0.0)) {
        return t_end;
    }
    cos_light = abs(cos_light);
    float sin_light = sqrt(max(1.0 - cos_light * cos_light, 0.0));
    float slope = TEXEL_REACH * p.texel_size * sin_light / max(cos_light, MIN_FACING);
    if (!map_holds_within(end, slope)) {
        return t_end;
    }
    float facing = max(abs(dot(normal, direction)), MIN_FACING);
    float tail = (p.bias * cos_light + TEXEL_REACH * p.texel_size * sin_light) / facing;
    return max(t_end - tail, t_start);
}

// The alpha and visibility of a ray from t_start to t_end whose light ends at `lit`,
// from the visibility of its stretch to `lit` (reference.rs: Marcher::dark_tail).
vec2 dark_tail(vec3 origin, vec3 direction, float t_start, float lit, float t_end,
               float visibility) {
    float sigma = p.extinction;
    float alpha = 0.0;
    float lit_weight = 0.0;
    float weight = 0.0;
    if (p.box_medium == BOX_NONE) {
        alpha = -expm1_accurate(-sigma * (t_end - t_start));
        lit_weight = integral_exp(sigma, lit - t_start);
        weight = integral_exp(sigma, t_end - t_start);
    } else {
        begin_ray(origin, direction);
        float a, b;
        if (box_segment(t_start, t_end, a, b)) {
            alpha = -expm1_accurate(-sigma * (b - a));
            lit_weight = lit > a ? box_integrate(a, min(lit, b), a, sigma) : 0.0;
            weight = box_integrate(a, b, a, sigma);
        }
    }
    float share = weight > 0.0 ? lit_weight / weight : (lit - t_start) / (t_end - t_start);
    return vec2(alpha, clamp(visibility * share, 0.0, 1.0));
}

// Adds one depth sample at `pixel` to a pixel's sums; `surface` < 0 is background.
void add_sample(vec2 pixel, float surface, inout vec3 radiance, inout float alpha,
                inout float visibility, inout float depth_sum) {
    bool background = surface < 0.0;
    vec3 origin_cam = p.origin0.xyz + pixel.x * p.origin_dx.xyz + pixel.y * p.origin_dy.xyz;
    vec3 dir_cam = p.dir0.xyz + pixel.x * p.dir_dx.xyz + pixel.y * p.dir_dy.xyz;
    float distance_per_depth = length(dir_cam);
    vec3 origin = (p.world_from_camera * vec4(origin_cam, 1.0)).xyz;
    vec3 direction = normalize(mat3(p.world_from_camera) * dir_cam);
    float t_start = p.clip_start * distance_per_depth;
    float t_end = background ? p.max_distance : min(surface, p.max_distance);
    float t_lit = lit_end(pixel, origin, direction, t_start, t_end);
    vec3 s = shade_sample(pixel, origin, direction, t_start, t_lit);
    if (t_lit < t_end) {
        s.yz = dark_tail(origin, direction, t_start, t_lit, t_end, s.z);
    }
    radiance += p.tint.rgb * (s.x * phase(direction));
    alpha += s.y;
    visibility += s.z;
    depth_sum += background ? p.max_distance : surface;
}

void shade_pixel(uvec2 id);

// The pixel of the output image `id` samples: its centre at full size (downsampled
// images take every stride-th pixel).
uvec2 full_pixel(uvec2 id) {
    return uvec2(min(id.x * p.stride + p.stride / 2u, p.full_width - 1u),
                 min(id.y * p.stride + p.stride / 2u, p.full_height - 1u));
}

// Where output pixel `id`'s ray ends, where all its depth samples agree (render.rs:
// uniform_surface): `surface` < 0 for background. False at a depth edge.
bool uniform_pixel_surface(uvec2 id, out float surface) {
    uvec2 full = full_pixel(id);
    uint ss = p.supersampling;
    uint sample_width = p.full_width * ss;
    float low = 1e30;
    float high = 0.0;
    float sum = 0.0;
    bool all_background = true;
    bool any_background = false;
    for (uint sy = 0; sy < ss; ++sy) {
        for (uint sx = 0; sx < ss; ++sx) {
            float s = surfaces[(full.y * ss + sy) * sample_width + full.x * ss + sx];
            bool background = s < 0.0;
            all_background = all_background && background;
            any_background = any_background || background;
            if (!background) {
                low = min(low, s);
                high = max(high, s);
                sum += s;
            }
        }
    }
    surface = all_background ? -1.0 : sum / float(ss * ss);
    return all_background || (!any_background && high <= low * (1.0 + EDGE_DEPTH_SPREAD));
}

void shade_output_pixel() {
    uvec2 id = gl_GlobalInvocationID.xy;
    if (id.x >= p.width || id.y >= p.height) {
        return;
    }
    shade_pixel(id);
}

void shade_pixel(uvec2 id) {
    uvec2 full = full_pixel(id);
    uint full_x = full.x;
    uint full_y = full.y;
    uint ss = p.supersampling;
    uint sample_width = p.full_width * ss;
    vec3 radiance = vec3(0.0);
    float alpha = 0.0;
    float visibility = 0.0;
    float depth_sum = 0.0;
    float spp = float(ss * ss);
    bool uniform_depth = false;
    if (ss > 1u) {
        // Shaded once at the centre, like MSAA, where no depth edge runs through the pixel.
        float surface;
        uniform_depth = uniform_pixel_surface(id, surface);
        if (uniform_depth) {
            vec2 centre = vec2(float(full_x), float(full_y)) + 0.5;
            add_sample(centre, surface, radiance, alpha, visibility, depth_sum);
        }
    }
    if (!uniform_depth) {
        for (uint sy = 0; sy < ss; ++sy) {
            for (uint sx = 0; sx < ss; ++sx) {
                float surface = surfaces[(full_y * ss + sy) * sample_width + full_x * ss + sx];
                vec2 pixel = vec2(float(full_x), float(full_y))
                    + (vec2(float(sx), float(sy)) + 0.5) / float(ss);
                add_sample(pixel, surface, radiance, alpha, visibility, depth_sum);
            }
        }
    }
    float count = uniform_depth ? 1.0 : spp;
    uint index = id.y * p.width + id.x;
    volume_out[index] = vec4(radiance / count, alpha / count);
    visibility_out[index] = visibility / count;
    depth_out[index] = depth_sum / count;
}
