#version 450
// Depth-aware joint-bilateral upsampling (core/src/upsample.rs): every full-size pixel
// blends its four surrounding low-resolution samples by bilinear distance times depth
// similarity, or takes the sample of the closest depth when none is similar. Where an
// opacity guide gives a pixel its exact opacity (at a fog box's silhouette), it blends
// the samples' radiance per unit opacity (blend_through_opacity).

layout(local_size_x = 8, local_size_y = 8) in;

layout(push_constant) uniform Push {
    uint width;        // full size
    uint height;
    uint low_width;
    uint low_height;
    uint factor;
    float tolerance;   // relative depth difference at which a weight falls to 1/e
    uint opacity_guided;  // whether `opacity_guide` holds a value per full-size pixel
    uint unused;
} pc;

layout(std430, binding = 0) readonly buffer LowVolume { vec4 low_volume[]; };
layout(std430, binding = 1) readonly buffer LowVisibility { float low_visibility[]; };
layout(std430, binding = 2) readonly buffer LowDepth { float low_depth[]; };
layout(std430, binding = 3) readonly buffer Guide { float guide[]; };
layout(std430, binding = 4) writeonly buffer Volume { vec4 volume_out[]; };
layout(std430, binding = 5) writeonly buffer Visibility { float visibility_out[]; };
// Exact opacity per full-size pixel, or negative where the samples' opacities agree.
layout(std430, binding = 6) readonly buffer OpacityGuide { float opacity_guide[]; };

// (first, second, fraction) of the samples around a full-size position.
void neighbours(float position, uint count, out uint first, out uint second, out float fraction) {
    float half_factor = float(pc.factor / 2u);
    float u = max((position - half_factor) / float(pc.factor), 0.0);
    first = min(uint(floor(u)), count - 1u);
    second = min(first + 1u, count - 1u);
    fraction = u - float(first);
}

void main() {
    uvec2 id = gl_GlobalInvocationID.xy;
    if (id.x >= pc.width || id.y >= pc.height) {
        return;
    }
    uint x0, x1, y0, y1;
    float fx, fy;
    neighbours(float(id.y), pc.low_height, y0, y1, fy);
    neighbours(float(id.x), pc.low_width, x0, x1, fx);
    float target = guide[id.y * pc.width + id.x];
    uint lw = pc.low_width;
    uint indices[4] = uint[4](y0 * lw + x0, y0 * lw + x1, y1 * lw + x0, y1 * lw + x1);
    float spatial[4] = float[4]((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy);
    float total = 0.0;
    vec4 rgba = vec4(0.0);
    float seen = 0.0;
    float closest = 3.0e38;
    uint closest_index = indices[0];
    uint closest_k = 0u;
    float weights[4];
    for (uint k = 0u; k < 4u; ++k) {
        uint index = indices[k];
        float difference = abs(low_depth[index] - target);
        if (difference < closest) {
            closest = difference;
            closest_index = index;
            closest_k = k;
        }
        float relative = difference / (pc.tolerance * max(abs(target), 1e-6));
        float weight = (spatial[k] + 1e-3) * exp(-relative * relative);
        weights[k] = weight;
        total += weight;
        rgba += weight * low_volume[index];
        seen += weight * low_visibility[index];
    }
    uint out_index = id.y * pc.width + id.x;
    float opacity = pc.opacity_guided != 0u ? opacity_guide[out_index] : -1.0;
    if (opacity >= 0.0) {
        vec3 radiance = vec3(0.0);
        float through = 0.0;
        float side_seen = 0.0, side_weight = 0.0, plain_seen = 0.0, plain_weight = 0.0;
        for (uint k = 0u; k < 4u; ++k) {
            float weight = total > 1e-6 ? weights[k] : (k == closest_k ? 1.0 : 0.0);
            vec4 sample_value = low_volume[indices[k]];
            float alpha = sample_value.a;
            radiance += weight * sample_value.rgb;
            through += weight * alpha;
            float side = opacity > 0.0 ? alpha : (alpha > 0.0 ? 0.0 : 1.0);
            float visibility = low_visibility[indices[k]];
            side_seen += weight * side * visibility;
            side_weight += weight * side;
            plain_seen += weight * visibility;
            plain_weight += weight;
        }
        float scale = through > 0.0 ? opacity / through : 0.0;
        volume_out[out_index] = vec4(radiance * scale, opacity);
        visibility_out[out_index] =
            side_weight > 0.0 ? side_seen / side_weight : plain_seen / plain_weight;
        return;
    }
    if (total > 1e-6) {
        volume_out[out_index] = rgba / total;
        visibility_out[out_index] = seen / total;
    } else {
        volume_out[out_index] = low_volume[closest_index];
        visibility_out[out_index] = low_visibility[closest_index];
    }
}
