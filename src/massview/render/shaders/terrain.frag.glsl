#version 330
// Forward per-pixel terrain shading (the reference the deferred path reproduces bit for bit):
// slopes and height come from the shading pyramid (one texture layer per resident block, any
// level), at the pyramid level matching the pixel footprint (terrain_lod.glsl,
// terrain_shading.glsl). Padding samples (beyond the input) are discarded when the store has
// any (PADDED).
uniform vec2 u_extent;        // last valid col, last valid row (finest samples)
in vec2 v_grid;
in float v_z;
out vec4 f_color;

float terrain_lod(vec2 gx, vec2 gy);
vec4 terrain_color(vec2 grid, float lod, float z);

void main() {
#if PADDED
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
#endif
    f_color = terrain_color(v_grid, terrain_lod(dFdx(v_grid), dFdy(v_grid)), v_z);
}
