#version 330
// Per-pixel terrain shading, decoupled from the geometric LOD: slopes and height come from
// the shading pyramid (one texture layer per resident block, any level), at the pyramid level
// matching the pixel footprint (trilinear between two levels); a block that is not resident
// falls back to its coarser ancestor. Lighting: a sun (GDAL azimuth/altitude) plus a sky
// hemisphere term, so slopes facing away from the sun keep their relief; aerial perspective
// blends towards the sky colour with distance. Padding samples (beyond the input) are discarded.
uniform vec2 u_extent;        // last valid col, last valid row (finest samples)
in vec2 v_grid;
in vec3 v_world;
out vec4 f_color;

vec4 terrain_color(vec2 grid, vec2 gx, vec2 gy, vec3 world);

void main() {
    if (v_grid.x > u_extent.x || v_grid.y > u_extent.y) discard;
    f_color = terrain_color(v_grid, dFdx(v_grid), dFdy(v_grid), v_world);
}
