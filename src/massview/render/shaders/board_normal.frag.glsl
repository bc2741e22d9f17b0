#version 330
// Pass 4 of 4: normal map, the unit world-space surface normal (RGBA32F target).
in vec3 v_normal;
out vec4 f_normal;
void main() { f_normal = vec4(normalize(v_normal), 1.0); }
