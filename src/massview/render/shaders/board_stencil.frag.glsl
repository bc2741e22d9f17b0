#version 330
// Pass 2 of 4: stencil map, 1 where the object's projection covers the pixel (R8 target).
out float f_cover;
void main() { f_cover = 1.0; }
