#version 330
// ID buffer: object id + 1 packed in RGB8 (24 bits; 0 = background).
uniform uint u_id;
out vec4 f_id;
void main() {
    f_id = vec4(float(u_id & 255u), float((u_id >> 8) & 255u), float((u_id >> 16) & 255u), 255.0) / 255.0;
}
