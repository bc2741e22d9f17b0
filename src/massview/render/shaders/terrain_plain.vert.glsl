#version 330
// Terrain K-patches drawn from M-block slots of one vertex buffer (vertex pulling by ID).
// gl_VertexID = index + baseVertex = slot*M*M + row*M + col; the per-slot instance attribute
// (fetched at baseInstance = slot) gives the block origin and sample step in finest-sample
// units. World coordinates come from exact integer sample indices, so a vertex shared by
// two patches (in two blocks or levels) gets bit-identical coordinates: no cracks.
uniform mat4 u_mvp;
uniform int u_M;
uniform vec3 u_scale;   // dx, dy (metres per finest sample), vertical scale
in float in_h;
in vec2 in_n;
in vec4 in_color;
in ivec4 in_slot;       // origin col, origin row, step, slot index
out vec3 v_normal;
out vec4 v_color;
void main() {
    int local = gl_VertexID - in_slot.w * u_M * u_M;
    int r = local / u_M;
    int c = local - r * u_M;
    int gx = in_slot.x + c * in_slot.z;
    int gy = in_slot.y + r * in_slot.z;
    vec3 p = vec3(float(gx) * u_scale.x, -float(gy) * u_scale.y, in_h * u_scale.z);
    gl_Position = u_mvp * vec4(p, 1.0);
    v_normal = vec3(in_n, sqrt(max(1.0 - dot(in_n, in_n), 0.0)));
    v_color = in_color;
}
