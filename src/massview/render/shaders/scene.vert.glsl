#version 330
// Scene objects: local positions and normals, per-instance camera-relative model matrix
// (columns in_m0..in_m3) and normal matrix (columns in_n0..in_n2), per-vertex RGBA8 colour.
uniform mat4 u_vp;  // projection * view rotation (eye at the origin)
in vec3 in_pos;
in vec3 in_normal;
in vec4 in_color;
in vec4 in_m0;
in vec4 in_m1;
in vec4 in_m2;
in vec4 in_m3;
in vec3 in_n0;
in vec3 in_n1;
in vec3 in_n2;
out vec3 v_normal;
out vec3 v_rel;  // the point relative to the eye (at the origin)
out vec4 v_color;
void main() {
    mat4 model = mat4(in_m0, in_m1, in_m2, in_m3);
    vec4 rel = model * vec4(in_pos, 1.0);
    gl_Position = u_vp * rel;
    v_rel = rel.xyz;
    v_normal = mat3(in_n0, in_n1, in_n2) * in_normal;
    v_color = in_color;
}
