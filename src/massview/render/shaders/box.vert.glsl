#version 330
// Occlusion-query boxes and ID-buffer meshes: world-space positions only.
uniform mat4 u_mvp;
in vec3 in_pos;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
