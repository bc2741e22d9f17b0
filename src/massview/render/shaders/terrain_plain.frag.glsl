#version 330
// Lit terrain colour; samples beyond the input extent (padding) are discarded.
uniform vec3 u_light;
uniform vec4 u_tint;
uniform vec2 u_extent;  // last valid col, last valid row (finest samples)
in vec3 v_normal;
in vec4 v_color;
in vec2 v_grid;
out vec4 f_color;
void main() {
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
    vec3 n = normalize(v_normal);
    float d = max(dot(n, u_light), 0.0);
    vec3 c = v_color.rgb * (0.45 + 0.7 * d);
    f_color = vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
}
