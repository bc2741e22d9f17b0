#version 330
// Terrain K-patches drawn from M-block slots of one vertex buffer (vertex pulling by ID).
// gl_VertexID = index + baseVertex = slot*M*M + row*M + col; the per-slot instance attribute
// (fetched at baseInstance = slot) gives the block origin and sample step in finest-sample
// units. World coordinates come from exact integer sample indices, so a vertex shared by
// two patches (in two blocks or levels) gets bit-identical coordinates: no cracks.
// Heights are exaggerated about the base: z = base + Z·(h·vertical_scale − base).
// BLOCK_M (samples per block side) is a compile-time constant, so the index arithmetic is
// multiplies and shifts. The fragment stages read v_grid and v_z (world x, y follow from the
// grid: terrain_shading.glsl); v_world is for transform feedback only (world_vertices).
uniform mat4 u_mvp;
const int u_M = BLOCK_M;
uniform vec3 u_scale;   // dx, dy (metres per finest sample), vertical scale
uniform vec2 u_exag;    // base (scaled height units), exaggeration Z
in float in_h;
in ivec4 in_slot;       // origin col, origin row, step, slot index
out vec2 v_grid;
out float v_z;
out vec3 v_world;
void main() {
    int local = gl_VertexID - in_slot.w * u_M * u_M;
    int r = local / u_M;
    int c = local - r * u_M;
    int gx = in_slot.x + c * in_slot.z;
    int gy = in_slot.y + r * in_slot.z;
    vec3 p = vec3(float(gx) * u_scale.x, -float(gy) * u_scale.y, u_exag.x + u_exag.y * (in_h * u_scale.z - u_exag.x));
    gl_Position = u_mvp * vec4(p, 1.0);
    v_grid = vec2(float(gx), float(gy));
    v_z = p.z;
    v_world = p;
}
