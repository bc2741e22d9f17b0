#version 330
// Reliefboard capture (§5.1): orthographic view of the object facing the board direction.
// u_view maps world to board coordinates (x right, y up, z towards the observer); u_proj is the
// orthographic projection of the cube [-r, r]^3; v_distance is measured from the front plane z = +r.
uniform mat4 u_view;
uniform mat4 u_proj;
uniform float u_radius;
in vec3 in_pos;
in vec3 in_normal;
in vec4 in_color;
out float v_distance;
out vec3 v_normal;
out vec4 v_color;
void main() {
    vec4 b = u_view * vec4(in_pos, 1.0);
    v_distance = u_radius - b.z;
    v_normal = in_normal;
    v_color = in_color;
    gl_Position = u_proj * b;
}
