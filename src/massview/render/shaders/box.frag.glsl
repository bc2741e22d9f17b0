#version 330
// Occlusion-query boxes: depth test only (colour and depth writes are masked off).
void main() {
}
