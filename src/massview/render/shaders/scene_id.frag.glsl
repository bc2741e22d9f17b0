#version 330
// ID buffer over the scene pool: object id + 1 packed in RGB8 (24 bits; 0 = background).
flat in uint v_id;
out vec4 f_id;
void main() {
    f_id = vec4(float(v_id & 255u), float((v_id >> 8) & 255u), float((v_id >> 16) & 255u), 255.0) / 255.0;
}
