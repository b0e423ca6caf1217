#version 450
// The shadow map's fragment shader: the object id of the triangle that passes the depth
// test lands in the R32_UINT attachment, in the same pass as its depth.

layout(location = 0) flat in uint object_id;
layout(location = 0) out uint id;

void main() {
    id = object_id;
}
