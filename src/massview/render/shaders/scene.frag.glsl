#version 330
// Unlit store colours lit at view time: a key light (two-sided Lambert), a sky/ground
// hemisphere ambient term by the normal's z; u_tint mixes a rank colour in.
uniform vec3 u_light;
uniform vec4 u_tint;
in vec3 v_normal;
in vec4 v_color;
out vec4 f_color;
void main() {
    vec3 n = normalize(v_normal);
    float key = abs(dot(n, u_light));
    float sky = 0.5 + 0.5 * n.z;
    vec3 c = v_color.rgb * (0.22 + 0.18 * sky + 0.6 * key);
    f_color = vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
}
