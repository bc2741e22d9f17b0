#version 330
// T2 (Röttger) fans as received by a visualization rank: per vertex the global sample index
// f = row * dim + col (uint32) and the height (float32); x and y come from the index
// (Gouranton et al. §3.2.1), so every rank computes bit-identical positions.
uniform mat4 u_mvp;
uniform uint u_dim;
uniform vec3 u_scale;   // dx, dy (metres per sample), vertical scale
uniform float u_zoffset;  // layer offset (world units)
in uint in_idx;
in float in_h;
in float in_rank;
out vec3 v_world;
out float v_h;
out vec2 v_grid;
flat out int v_rank;
void main() {
    uint row = in_idx / u_dim;
    uint col = in_idx - row * u_dim;
    vec3 p = vec3(float(col) * u_scale.x, -float(row) * u_scale.y, in_h * u_scale.z + u_zoffset);
    gl_Position = u_mvp * vec4(p, 1.0);
    v_world = p;
    v_h = in_h;
    v_grid = vec2(float(col), float(row));
    v_rank = int(in_rank);
}
