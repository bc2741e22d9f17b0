#version 330
// Two-sided Lambert shading with a fixed directional light; u_tint mixes a rank color in.
uniform vec3 u_light;
uniform vec4 u_tint;
in vec3 v_normal;
in vec4 v_color;
out vec4 f_color;
void main() {
    vec3 n = normalize(v_normal);
    float d = abs(dot(n, u_light));
    vec3 c = v_color.rgb * (0.35 + 0.65 * d);
    f_color = vec4(mix(c, u_tint.rgb, u_tint.a), 1.0);
}
