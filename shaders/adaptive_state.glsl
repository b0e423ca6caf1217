// Adaptive shading's state (core/src/gpu/prefiltered.rs: STATE_BYTES, ARGS_OFFSET,
// SHADED_WORD), shared by prefiltered.comp and adaptive_floor.comp; each defines
// ADAPTIVE_STATE_BINDING before including it.
layout(std430, binding = ADAPTIVE_STATE_BINDING) buffer AdaptiveState {
    uint listed;        // appended by EDGES and CENTRES
    uint to_shade;      // LISTED's count, set by ARGS
    uint shaded;        // pixels shaded in all
    uint unused;
    uvec4 args;         // LISTED's workgroups (the indirect dispatch's arguments)
    vec4 floor_rgba;    // per channel, the value below which spreads are held to it
} state;
