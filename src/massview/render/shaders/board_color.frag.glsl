#version 330
// Pass 3 of 4: colour map, the unlit vertex colour (RGBA8 target).
in vec4 v_color;
out vec4 f_color;
void main() { f_color = v_color; }
