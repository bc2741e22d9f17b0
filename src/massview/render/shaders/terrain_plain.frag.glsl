#version 330
// Lit terrain colour. No discard: the mesh is the grid it was given, so no fragment lies beyond
// it (the discard of samples past the grid's own extent never fired), and a discard turns off
// the early depth test: at full resolution (~25 triangles a pixel) every fragment is shaded.
uniform vec3 u_light;
uniform vec4 u_tint;
in vec3 v_normal;
in vec4 v_color;
out vec4 f_color;
void main() {
    vec3 n = normalize(v_normal);
    float d = max(dot(n, u_light), 0.0);
    vec3 c = v_color.rgb * (0.45 + 0.7 * d);
    f_color = vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
}
