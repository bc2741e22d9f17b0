#version 330
// Object meshes: world-space positions and normals, per-vertex RGBA8 color.
uniform mat4 u_mvp;
in vec3 in_pos;
in vec3 in_normal;
in vec4 in_color;
out vec3 v_normal;
out vec4 v_color;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_normal = in_normal;
    v_color = in_color;
}
