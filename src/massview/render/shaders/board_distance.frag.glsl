#version 330
// Pass 1 of 4: distance map (world units from the board's front plane), R32F target.
in float v_distance;
out float f_distance;
void main() { f_distance = v_distance; }
