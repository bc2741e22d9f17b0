#version 330
// ID buffer over the scene pool: local positions, per-instance camera-relative model matrix
// (columns in_m0..in_m3) and object id + 1 (in_id, exact in float32 below 2^24).
uniform mat4 u_vp;  // projection * view rotation (eye at the origin)
in vec3 in_pos;
in vec4 in_m0;
in vec4 in_m1;
in vec4 in_m2;
in vec4 in_m3;
in float in_id;
flat out uint v_id;
void main() {
    mat4 model = mat4(in_m0, in_m1, in_m2, in_m3);
    gl_Position = u_vp * (model * vec4(in_pos, 1.0));
    v_id = uint(in_id);
}
