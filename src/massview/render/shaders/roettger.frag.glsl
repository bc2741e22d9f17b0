#version 330
// Height-tinted, flat-lit terrain (facet normal from screen-space derivatives); padding
// samples beyond the input extent are discarded; u_tint_on mixes in a colour per
// computation rank (the rank that produced the fan).
uniform vec3 u_light;
uniform vec2 u_extent;   // last valid col, last valid row
uniform vec2 u_zrange;   // height range for the colour ramp
uniform int u_tint_on;
uniform vec3 u_tints[8];
in vec3 v_world;
in float v_h;
in vec2 v_grid;
flat in int v_rank;
out vec4 f_color;
void main() {
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
    vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    if (n.z < 0.0) n = -n;
    float u = clamp((v_h - u_zrange.x) / max(u_zrange.y - u_zrange.x, 1e-6), 0.0, 1.0);
    vec3 low = vec3(0.32, 0.52, 0.30), mid = vec3(0.62, 0.55, 0.40), high = vec3(0.92, 0.92, 0.90);
    vec3 base = u < 0.5 ? mix(low, mid, u * 2.0) : mix(mid, high, u * 2.0 - 1.0);
    vec3 c = base * (0.40 + 0.75 * max(dot(n, u_light), 0.0));
    if (u_tint_on != 0) c = mix(c, u_tints[v_rank % 8], 0.55);
    f_color = vec4(c, 1.0);
}
