#version 450
// The depth passes' vertex shader for frames with alpha-cut triangles
// (`core/src/gpu/raster.rs`): `raster.vert`, plus each corner's texture coordinates,
// interpolated perspective-correctly, and its triangle's mask for the fragment shader.

layout(std430, set = 0, binding = 0) readonly buffer Positions { float positions[]; };
layout(std430, set = 0, binding = 1) readonly buffer Corners { uint corners[]; };
layout(std430, set = 0, binding = 2) readonly buffer ObjectIds { uint object_ids[]; };
layout(std430, set = 0, binding = 3) readonly buffer Uvs { float uvs[]; };
layout(std430, set = 0, binding = 4) readonly buffer TriangleMasks { uint triangle_masks[]; };

layout(push_constant) uniform Push {
    mat4 clip_from_world;
};

layout(location = 0) flat out uint object_id;
layout(location = 1) out vec2 uv;
layout(location = 2) flat out uint mask;

void main() {
    uint vertex = corners[gl_VertexIndex];
    vec3 world = vec3(positions[3 * vertex], positions[3 * vertex + 1], positions[3 * vertex + 2]);
    gl_Position = clip_from_world * vec4(world, 1.0);
    object_id = object_ids[gl_VertexIndex / 3];
    uv = vec2(uvs[2 * vertex], uvs[2 * vertex + 1]);
    mask = triangle_masks[gl_VertexIndex / 3];
}
