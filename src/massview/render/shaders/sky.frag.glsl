#version 330
// Sky gradient behind the terrain (depth untouched: the background stays at the far plane).
uniform mat4 u_inv_mvp;
uniform vec3 u_eye;
in vec2 v_ndc;
out vec4 f_color;
vec3 sky_color(vec3 dir);
void main() {
    vec4 p = u_inv_mvp * vec4(v_ndc, 0.0, 1.0);
    f_color = vec4(sky_color(p.xyz / p.w - u_eye), 1.0);
}
