#version 450
// The depth passes' vertex shader (`core/src/gpu/raster.rs`). Vertices are pulled from
// storage buffers: a non-indexed draw of 3·T vertices, where vertex 3t + c is corner c of
// triangle t, so that each triangle carries its own object id to the fragment shader.

layout(std430, set = 0, binding = 0) readonly buffer Positions { float positions[]; };
layout(std430, set = 0, binding = 1) readonly buffer Corners { uint corners[]; };
layout(std430, set = 0, binding = 2) readonly buffer ObjectIds { uint object_ids[]; };

layout(push_constant) uniform Push {
    // World to Vulkan clip space: x and y reach the target's pixels through the viewport,
    // z holds the encoded depth (see `DepthEncoding`), w the projection's w.
    mat4 clip_from_world;
};

layout(location = 0) flat out uint object_id;

void main() {
    uint vertex = corners[gl_VertexIndex];
    vec3 world = vec3(positions[3 * vertex], positions[3 * vertex + 1], positions[3 * vertex + 2]);
    gl_Position = clip_from_world * vec4(world, 1.0);
    object_id = object_ids[gl_VertexIndex / 3];
}
